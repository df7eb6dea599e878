"""Model registry commands: promote, import, export, dashboard, models list."""

from __future__ import annotations

import argparse
from pathlib import Path

from mmm.cli.common import DEFAULT_TRACKING_URI, CLIError, refuse_existing
from mmm.kinds import KINDS, PROMOTABLE


def add_promote(sub) -> None:
    promote = sub.add_parser(
        "promote", help="measure a candidate, register it, move `champion` only when it wins"
    )
    promote.add_argument("kind", choices=list(PROMOTABLE))
    promote.add_argument(
        "overrides",
        nargs="*",
        help="e.g. candidate=RUN_ID criteria.text2motion=[{metric: generated/fid, mode: min, margin: 0.01}]",
    )
    promote.set_defaults(func=cmd_promote)


def add_import(sub) -> None:
    imp = sub.add_parser(
        "import", help="the authors' released checkpoints as this package's models, registered in MLflow"
    )
    imp.add_argument(
        "kind",
        choices=["released", "released-upperbody"],
        help="released: the text-to-motion pair; released-upperbody: refused (see the README)",
    )
    imp.add_argument(
        "--vq",
        required=True,
        help="released stage-1 checkpoint ({'net': state_dict}, e.g. output/vq/.../net_last.pth)",
    )
    imp.add_argument(
        "--transformer",
        default=None,
        help="released stage-2 checkpoint ({'trans': state_dict}); left out: the tokenizer only",
    )
    imp.add_argument(
        "--stats",
        required=True,
        help="folder with the mean.npy/std.npy the release normalizes with (the T2M evaluator's meta folder)",
    )
    imp.add_argument(
        "--clip",
        default=None,
        help="OpenAI CLIP ViT-B/32 weights (ViT-B-32.pt, read without running it) or open_clip's",
    )
    imp.add_argument(
        "--clip-vocab",
        default=None,
        help="bpe_simple_vocab_16e6.txt.gz (default: the one inside an installed open_clip)",
    )
    imp.add_argument(
        "--alias",
        default="released",
        help="alias given to the registered versions (not champion: promotion moves that)",
    )
    imp.add_argument(
        "--heads",
        type=int,
        default=None,
        help="attention heads (default: embedding width / 64, the release's 16)",
    )
    imp.add_argument(
        "--out-dir", default="outputs/imported", help="where this package's checkpoints are written"
    )
    imp.add_argument("--tracking-uri", default=DEFAULT_TRACKING_URI)
    imp.add_argument("--no-register", action="store_true", help="only write the checkpoints")
    imp.set_defaults(func=cmd_import)


def add_export(sub) -> None:
    exp = sub.add_parser("export", help="a model in the authors' released file layout")
    exp.add_argument("kind", choices=["released"])
    exp.add_argument(
        "--model", required=True, help="a released-variant model: checkpoint, run id or models:/NAME@ALIAS"
    )
    exp.add_argument(
        "--out", required=True, help="folder for vq.pth ({'net': ...}) and trans.pth ({'trans': ...})"
    )
    exp.add_argument("--tracking-uri", default=DEFAULT_TRACKING_URI)
    exp.add_argument("--overwrite", action="store_true", help="replace vq.pth and trans.pth already in --out")
    exp.set_defaults(func=cmd_export)


def add_dashboard(sub) -> None:
    dash = sub.add_parser(
        "dashboard",
        help="links into the MLflow dashboard: every experiment in its "
        "training view, its newest run, the models",
    )
    dash.add_argument("--tracking-uri", default=DEFAULT_TRACKING_URI)
    dash.add_argument("--host", default="127.0.0.1")
    dash.add_argument("--port", type=int, default=5000)
    dash.add_argument(
        "--url", default=None, help="the dashboard's address when it is served elsewhere (e.g. a team server)"
    )
    dash.set_defaults(func=cmd_dashboard)


def add_models(sub) -> None:
    models = sub.add_parser("models", help="registered models (`mmm models` is `mmm models list`)")
    models.add_argument("--tracking-uri", default=DEFAULT_TRACKING_URI)
    models.set_defaults(func=cmd_models)
    commands = models.add_subparsers(dest="models_command")
    listing = commands.add_parser("list", help="versions, aliases and metrics of the registered models")
    # SUPPRESS: a --tracking-uri given before `list` is not reset to the default by the subcommand
    listing.add_argument("--tracking-uri", default=argparse.SUPPRESS)


def cmd_promote(args: argparse.Namespace) -> None:
    # imported here: keeps `mmm --help` fast
    from mmm.registry.configs import load_promote_config

    cfg = load_promote_config(args.overrides)  # checked before the promotion's imports
    from mmm.registry.promote import promote

    decision = promote(args.kind, cfg)
    name = PROMOTABLE[args.kind].registered
    print(f"{name} version {decision.version} -> {decision.alias}: {decision.reason}")
    for line in decision.comparisons:
        print(f"  {line}")


def cmd_import(args: argparse.Namespace) -> None:
    from mmm.released.importer import UPPER_BODY_REFUSAL, import_released

    if args.kind == "released-upperbody":
        raise CLIError(UPPER_BODY_REFUSAL)
    result = import_released(
        args.vq,
        args.stats,
        args.transformer,
        args.clip,
        args.clip_vocab,
        args.alias,
        args.heads,
        args.out_dir,
        args.tracking_uri,
        register=not args.no_register,
    )
    print(f"tokenizer checkpoint: {result.tokenizer_checkpoint}")
    if result.transformer_checkpoint:
        print(f"transformer checkpoint: {result.transformer_checkpoint}")
    if result.tokenizer_version:
        tokenizer, text2motion = KINDS["stage1"].registered, KINDS["stage2"].registered
        both = f", models:/{text2motion}/{result.text2motion_version} (@{result.alias})"
        print(
            f"registered{' (already imported: reused)' if result.reused else ''}: "
            f"models:/{tokenizer}/{result.tokenizer_version} (@{result.alias})"
            + (both if result.text2motion_version else "")
        )
    if result.text2motion_version:
        model = f"models:/{KINDS['stage2'].registered}@{result.alias}"
        print(
            f"generate with: mmm generate --model {model} --text '...' --length 120 --out outputs/gen"
            " [--decoding released]"
        )


def cmd_export(args: argparse.Namespace) -> None:
    import torch

    from mmm.generation.model import TextToMotion
    from mmm.released.importer import export_released

    out = Path(args.out)
    names = ("vq.pth", "trans.pth")
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out} is a file: name a folder for {' and '.join(names)}")
    for name in names:
        refuse_existing(out / name, args.overwrite, "--out folder")
    model = TextToMotion.load(args.model, tracking_uri=args.tracking_uri)
    net, trans = export_released(model.tokenizer, model.transformer)
    out.mkdir(parents=True, exist_ok=True)
    for name, obj in zip(names, (net, trans)):
        tmp = out / f".{name}.tmp"
        torch.save(obj, tmp)
        tmp.replace(out / name)
        print(f"wrote {out / name}")


def cmd_dashboard(args: argparse.Namespace) -> None:
    from mlflow.tracking import MlflowClient

    from mmm.tracking import dashboard_links, store_for_reading

    if not 1 <= args.port <= 65535:
        raise CLIError(
            f"--port {args.port} is not allowed: a TCP port from 1 to 65535 (make mlflow-ui uses 5000)"
        )
    client = MlflowClient(store_for_reading(args.tracking_uri))
    base = args.url or f"http://{args.host}:{args.port}"
    print(f"The MLflow dashboard (make mlflow-ui serves it on {base}); each experiment in its training view:")
    for line in dashboard_links(client, base):
        print(f"  {line}")


def cmd_models(args: argparse.Namespace) -> None:
    from mlflow.tracking import MlflowClient

    from mmm.registry.versions import list_models
    from mmm.tracking import store_for_reading

    print(list_models(MlflowClient(store_for_reading(args.tracking_uri))))

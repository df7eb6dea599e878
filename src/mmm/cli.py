"""The `mmm` command: data, conversion, rendering (training, generation and promotion join as they land).

Every subcommand exits 0 on success and 2 with a one-paragraph error (file, value, fix) on bad input.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("mmm")


class CLIError(Exception):
    pass


def _load_npy(path: str) -> np.ndarray:
    p = Path(path)
    if not p.exists():
        raise CLIError(f"{p}: no such file")
    try:
        return np.load(p, allow_pickle=False)
    except Exception as e:
        raise CLIError(f"{p}: cannot read as .npy ({e})") from None


def _save_npy(path: str, array: np.ndarray) -> None:
    from mmm.data.humanml3d import save_array_atomic

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_array_atomic(out, array)
    print(f"wrote {out} {tuple(array.shape)}")


def cmd_convert(args: argparse.Namespace) -> None:
    from mmm.motion.features import joints_to_features, recover_from_ric
    from mmm.motion.skeleton import skeleton_for

    arr = _load_npy(args.input)
    if not np.isfinite(arr).all():
        raise CLIError(f"{args.input}: contains NaN/Inf values; fix the motion first")
    if args.direction == "joints-to-features":
        if arr.ndim != 3 or arr.shape[1:] not in ((22, 3), (21, 3)) or arr.shape[0] < 2:
            raise CLIError(f"{args.input}: shape {arr.shape}, expected joints (T, 22, 3) or (T, 21, 3) with T >= 2")
        out = joints_to_features(arr.astype(np.float32), skeleton_for(arr.shape[1]), retarget=not args.no_retarget)
    else:
        if arr.ndim != 2 or arr.shape[1] not in (263, 251) or arr.shape[0] < 1:
            raise CLIError(f"{args.input}: shape {arr.shape}, expected features (T, 263) or (T, 251)")
        out = recover_from_ric(arr.astype(np.float32))
    _save_npy(args.output, out.astype(np.float32))


def cmd_data_synth(args: argparse.Namespace) -> None:
    from mmm.data.synthetic.generate import generate_dataset

    summary = generate_dataset(args.out, num_clips=args.num_clips, seed=args.seed, overwrite=args.overwrite)
    print(summary)


def cmd_data_stats(args: argparse.Namespace) -> None:
    from mmm.data.humanml3d import compute_stats, save_array_atomic
    from mmm.motion.features import FeatureLayout
    from mmm.motion.skeleton import SKELETONS

    root = Path(args.root)
    num_joints = SKELETONS[args.skeleton].num_joints
    mean, std, report = compute_stats(root, num_joints)
    print(f"{root}: statistics over {report.kept_clips} files")
    if report.skipped:
        print(report.summary())
    layout = FeatureLayout(num_joints)
    names = ("root yaw vel", "root xz vel", "root height", "positions", "rotations", "velocities", "contacts")
    have = (root / "Mean.npy").exists() and (root / "Std.npy").exists()
    old_mean = np.load(root / "Mean.npy") if have else None
    old_std = np.load(root / "Std.npy") if have else None
    print(f"{'group':14s} {'mean(avg)':>10s} {'std':>10s}" + (f" {'saved std':>10s} {'max|dmean|':>10s}" if have else ""))
    for name, sl in zip(names, layout.groups()):
        row = f"{name:14s} {mean[sl].mean():10.4f} {std[sl][0]:10.4f}"
        if have:
            row += f" {old_std[sl][0]:10.4f} {np.abs(old_mean[sl] - mean[sl]).max():10.2e}"
        print(row)
    if args.write:
        save_array_atomic(root / "Mean.npy", mean)
        save_array_atomic(root / "Std.npy", std)
        print(f"wrote {root / 'Mean.npy'} and {root / 'Std.npy'}")


def cmd_data_check(args: argparse.Namespace) -> None:
    from mmm.data.humanml3d import check_mirror_splits, load_items, load_stats
    from mmm.motion.skeleton import SKELETONS

    sk = SKELETONS[args.skeleton]
    min_length = args.min_length or (24 if sk.name == "kit" else 40)
    root = Path(args.root)
    load_stats(root, sk.feature_dim)
    for split in ("train", "val", "test"):
        _, report = load_items(root, split, feature_dim=sk.feature_dim, fps=sk.fps, min_length=min_length, on_invalid=args.on_invalid)
        print(f"{split}: {report.summary()}")
    leaks = check_mirror_splits(root)
    print(f"mirrored ids in a different split from their original: {len(leaks)}" + (f" (e.g. {', '.join(leaks[:5])})" if leaks else ""))


def cmd_data_preview(args: argparse.Namespace) -> None:
    from mmm.data.preview import preview_dataset

    for path in preview_dataset(args.root, args.out, count=args.count, split=args.split):
        print(f"wrote {path}")


def cmd_render(args: argparse.Namespace) -> None:
    from mmm.render import render_files

    for path in render_files(args.inputs, args.out, captions=args.caption or None, fps=args.fps):
        print(f"wrote {path}")


def cmd_train(args: argparse.Namespace) -> None:
    if args.stage == "stage1":
        from mmm.training.stage1 import load_stage1_config, train_stage1

        result = train_stage1(load_stage1_config(args.overrides), resume=args.resume)
    else:
        from mmm.training.stage2 import load_stage2_config, train_stage2

        result = train_stage2(load_stage2_config(args.overrides), resume=args.resume)
    if result.run_id is None and not result.best_checkpoint:
        return  # a non-zero rank of a distributed run
    print(f"MLflow run: {result.run_id}")
    print(f"checkpoints: best {result.best_checkpoint}, last {result.last_checkpoint}")
    shown = {k: v for k, v in sorted(result.metrics.items()) if k.startswith("val/")}
    print("validation: " + ", ".join(f"{k}={v:.4g}" for k, v in shown.items()))


def cmd_tokenize(args: argparse.Namespace) -> None:
    from mmm.training.stage2 import load_stage2_config, prepare_stage2_data

    datamodule = prepare_stage2_data(load_stage2_config(args.overrides))
    print(f"tokens: {datamodule.tokens.folder} ({len(datamodule.tokens)} motions)")
    print(f"caption embeddings: {len(datamodule.caption_cache)} captions ({datamodule.text_encoder.identity})")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mmm", description="MMM: text-to-motion training, generation and tracking")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    convert = sub.add_parser("convert", help="joint positions <-> 263-d features")
    convert.add_argument("direction", choices=["joints-to-features", "features-to-joints"])
    convert.add_argument("input", help="(T, 22, 3) joints or (T, 263) features .npy")
    convert.add_argument("output", help=".npy to write")
    convert.add_argument("--no-retarget", action="store_true", help="keep the motion's own bone lengths")
    convert.set_defaults(func=cmd_convert)

    data = sub.add_parser("data", help="datasets: synthesize, statistics, checks, previews").add_subparsers(dest="data_command", required=True)
    synth = data.add_parser("synth", help="generate the synthetic text-motion dataset")
    synth.add_argument("--out", required=True)
    synth.add_argument("--num-clips", type=int, default=1500)
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    synth.set_defaults(func=cmd_data_synth)

    stats = data.add_parser("stats", help="Mean/Std of a dataset computed the reference way")
    stats.add_argument("root")
    stats.add_argument("--skeleton", choices=["t2m", "kit"], default="t2m")
    stats.add_argument("--write", action="store_true", help="write Mean.npy and Std.npy into the dataset")
    stats.set_defaults(func=cmd_data_stats)

    check = data.add_parser("check", help="load every split and report what is kept and left out")
    check.add_argument("root")
    check.add_argument("--skeleton", choices=["t2m", "kit"], default="t2m")
    check.add_argument("--min-length", type=int, default=None)
    check.add_argument("--on-invalid", choices=["error", "skip"], default="skip")
    check.set_defaults(func=cmd_data_check)

    preview = data.add_parser("preview", help="render a few clips of a dataset (one per action when labelled)")
    preview.add_argument("root")
    preview.add_argument("--out", required=True)
    preview.add_argument("--count", type=int, default=6)
    preview.add_argument("--split", default="test")
    preview.set_defaults(func=cmd_data_preview)

    train = sub.add_parser("train", help="train a stage; any config key can be overridden as key=value")
    train.add_argument("stage", choices=["stage1", "stage2"])
    train.add_argument("overrides", nargs="*", help="e.g. trainer.max_steps=500 model=paper data=humanml3d")
    train.add_argument("--resume", default=None, help="'last' (newest run of this stage) or a checkpoint path")
    train.set_defaults(func=cmd_train)

    tokenize = sub.add_parser("tokenize", help="tokenize a dataset with a stage-1 model and cache caption embeddings (stage 2's inputs)")
    tokenize.add_argument("overrides", nargs="*", help="stage 2's config keys, e.g. stage1=RUN_ID data=humanml3d")
    tokenize.set_defaults(func=cmd_tokenize)

    render = sub.add_parser("render", help="stick-figure GIF/MP4/PNG of motions side by side")
    render.add_argument("inputs", nargs="+", help=".npy files of joints (T, 22, 3) or features (T, 263)")
    render.add_argument("--out", required=True, help="FILE.gif, FILE.mp4 or FILE.png (contact sheet)")
    render.add_argument("--caption", action="append", help="one per input, in order")
    render.add_argument("--fps", type=float, default=None)
    render.set_defaults(func=cmd_render)
    return parser


def _configure_logging(verbose: bool) -> None:
    """This package's INFO lines and everyone's warnings, once each (Lightning prints its own
    INFO lines through its own handler)."""
    fmt = logging.Formatter("%(levelname)s %(name)s: %(message)s")
    logging.basicConfig(level=logging.WARNING)
    for handler in logging.getLogger().handlers:
        handler.setLevel(logging.DEBUG if verbose else logging.WARNING)
        handler.setFormatter(fmt)
    ours = logging.getLogger("mmm")
    ours.setLevel(logging.DEBUG if verbose else logging.INFO)
    if not ours.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(fmt)
        ours.addHandler(handler)
        ours.propagate = False


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _configure_logging(args.verbose)
    from mmm.config import ConfigError
    from mmm.data.humanml3d import DataError

    try:
        args.func(args)
    except (CLIError, DataError, ConfigError, FileExistsError, FileNotFoundError, ValueError) as e:
        if args.verbose:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

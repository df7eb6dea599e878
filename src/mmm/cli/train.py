"""Training and evaluation commands: train, tokenize, evaluate, ablate, pipeline."""

from __future__ import annotations

import argparse

from mmm.cli.common import CLIError
from mmm.kinds import KINDS


def add_train(sub) -> None:
    train = sub.add_parser("train", help="train a stage; any config key can be overridden as key=value")
    train.add_argument(
        "stage",
        choices=list(KINDS),
        help="stage1-parts/stage2-parts: the part-aware model for upper-body editing",
    )
    train.add_argument("overrides", nargs="*", help="e.g. trainer.max_steps=500 model=paper data=humanml3d")
    train.add_argument(
        "--resume",
        default=None,
        help="'last' (newest run of this stage that no other process is writing) or a "
        "checkpoint path (one outside this stage's run folders is only read: the run goes on "
        "in a new run folder)",
    )
    train.set_defaults(func=cmd_train)


def add_tokenize(sub) -> None:
    tokenize = sub.add_parser(
        "tokenize",
        help="tokenize a dataset with a stage-1 model and cache caption embeddings (stage 2's inputs)",
    )
    tokenize.add_argument(
        "overrides", nargs="*", help="stage 2's config keys, e.g. stage1=RUN_ID data=humanml3d"
    )
    tokenize.set_defaults(func=cmd_tokenize)


def add_evaluate(sub) -> None:
    evaluate = sub.add_parser(
        "evaluate",
        help="the evaluation protocol, reconstruction metrics and prompt adherence, logged to MLflow",
    )
    evaluate.add_argument(
        "overrides",
        nargs="*",
        help="e.g. text2motion=RUN_ID protocol.replications=5 evaluator.reference=t2m:/ckpt/t2m",
    )
    evaluate.set_defaults(func=cmd_evaluate)


def add_ablate(sub) -> None:
    ablate = sub.add_parser("ablate", help="the supplementary's ablation tables (8-13) as sweeps")
    ablate.add_argument("kind", choices=["reset", "cross-layers", "schedule", "temperature", "topk", "topp"])
    ablate.add_argument(
        "overrides", nargs="*", help="e.g. grids.temperature=[0.5,1.0] protocol.replications=5"
    )
    ablate.set_defaults(func=cmd_ablate)


def add_pipeline(sub) -> None:
    pipeline = sub.add_parser(
        "pipeline", help="stages chained as one MLflow parent run; unchanged steps are skipped"
    )
    pipeline.add_argument("name", choices=["full", "stage1", "stage2", "evaluate", "promote", "parts"])
    pipeline.add_argument(
        "overrides", nargs="*", help="e.g. overrides.stage1=[trainer.max_steps=500] data=humanml3d"
    )
    pipeline.add_argument(
        "--force",
        action="append",
        default=[],
        help="rerun this step even if its inputs did not change (or 'all')",
    )
    pipeline.set_defaults(func=cmd_pipeline)


def cmd_train(args: argparse.Namespace) -> None:
    kind = KINDS[args.stage]
    # imported here: keeps `mmm --help` fast. Each config is composed and checked before its trainer
    # (and Lightning) is imported, so that a bad one is refused in about a second.
    from mmm.training import configs

    if kind.name in ("stage1", "stage1-parts"):
        cfg = configs.load_stage1_config(args.overrides, parts=kind.part_aware)
        from mmm.training.stage1 import train_stage1

        result = train_stage1(cfg, resume=args.resume)
    elif kind.name == "length":
        if args.resume:
            raise CLIError("--resume is not supported for the length estimator (it trains in seconds)")
        cfg = configs.load_length_config(args.overrides)
        from mmm.training.length import train_length

        result = train_length(cfg)
    elif kind.name == "evaluator":
        if args.resume:
            raise CLIError("--resume is not supported for the evaluator (it trains in a few minutes)")
        cfg = configs.load_evaluator_config(args.overrides)
        from mmm.training.evaluator import train_evaluator

        result = train_evaluator(cfg)
    else:
        cfg = configs.load_stage2_config(args.overrides, parts=kind.part_aware)
        from mmm.training.stage2 import train_stage2

        result = train_stage2(cfg, resume=args.resume)
    from lightning.pytorch.utilities import rank_zero_only

    if rank_zero_only.rank != 0 or (result.run_id is None and not result.best_checkpoint):
        return  # a non-zero rank of a distributed run: rank 0 reports
    print(f"MLflow run: {result.run_id}")
    print(f"checkpoints: best {result.best_checkpoint}, last {result.last_checkpoint}")
    shown = {k: v for k, v in sorted(result.metrics.items()) if k.startswith("val/")}
    print("validation: " + (", ".join(f"{k}={v:.4g}" for k, v in shown.items()) or "none in this launch"))
    if getattr(result, "model_version", None):
        tested = [
            (k, v)
            for k, v in sorted(result.metrics.items())
            if k.startswith("test/r_precision") or k == "test/matching_distance"
        ]
        print("test: " + ", ".join(f"{k}={v:.4g}" for k, v in tested))
        print(f"registered: models:/{result.registered_model}/{result.model_version}")


def cmd_tokenize(args: argparse.Namespace) -> None:
    from mmm.training.configs import load_stage2_config

    cfg = load_stage2_config(args.overrides)
    from mmm.training.stage2 import prepare_stage2_data

    datamodule = prepare_stage2_data(cfg)
    print(f"tokens: {datamodule.tokens.folder} ({len(datamodule.tokens)} motions)")
    encoder = datamodule.text_encoder.identity
    print(f"caption embeddings: {len(datamodule.caption_cache)} captions ({encoder})")


def cmd_evaluate(args: argparse.Namespace) -> None:
    from mmm.evaluation.configs import load_evaluate_config

    cfg = load_evaluate_config(args.overrides)
    from mmm.evaluation.run import evaluate

    results = evaluate(cfg)
    print(results["table"])
    for path in results.get("samples", []):
        print(f"wrote {path}")
    if results.get("run_id"):
        print(f"MLflow run: {results['run_id']} (experiment mmm-evaluation)")


def cmd_ablate(args: argparse.Namespace) -> None:
    from mmm.evaluation.configs import load_ablation_config

    cfg = load_ablation_config(args.overrides, args.kind)
    from mmm.evaluation.ablation import run_ablation

    result = run_ablation(args.kind, cfg)
    print(result["table"])
    for path in result["files"]:
        print(f"wrote {path}")


def cmd_pipeline(args: argparse.Namespace) -> None:
    from mmm.pipeline.configs import load_pipeline_config

    config = load_pipeline_config(args.overrides)
    from mmm.pipeline.steps import run_pipeline

    reports = run_pipeline(args.name, config, force=args.force, overrides=args.overrides)
    for r in reports:
        shown = ", ".join(f"{k}={v}" for k, v in r.outputs.items() if k in ("run_id", "version", "alias"))
        print(f"{r.name:22s} {r.status:8s} {r.seconds:7.1f} s  " + shown)
        if r.outputs.get("reason"):
            print(f"{'':22s} {r.outputs['reason']}")

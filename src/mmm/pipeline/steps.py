"""The pipelines: which steps, what each consumes, how it runs (conf/pipeline.yaml configures them).

    full:      evaluator -> promote-evaluator -> stage1 -> promote-tokenizer -> tokenize -> stage2
               -> length -> evaluate -> promote-text2motion
    stage1:    stage1 -> promote-tokenizer
    stage2:    tokenize -> stage2 -> length
    evaluate:  evaluate
    promote:   promote-evaluator, promote-tokenizer, promote-text2motion (of the newest runs)
    parts:     stage1-parts -> stage2-parts -> promote-upperbody (the part-aware model for
               upper-body editing; overrides.stage1_parts / overrides.stage2_parts)

Stage 2 tokenizes with the tokenizer champion (the promoted one) when it was measured on the
pipeline's data, so the transformer and the champion tokenizer agree; on other data (a recipe with
a dataset of its own) with the pipeline's own stage-1 run. Every step writes to the same tracking
store and data.
"""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig

from mmm.config import config_hash, to_object
from mmm.data.datamodule import TokenizerDataModule
from mmm.evaluation.configs import load_evaluate_config
from mmm.evaluation.run import evaluate
from mmm.fingerprint import dataset_fingerprint
from mmm.kinds import PROMOTABLE
from mmm.pipeline.configs import PipelineConfig, shared_overrides
from mmm.pipeline.runner import Context, Step, StepReport, run_steps
from mmm.registry import versions
from mmm.registry.configs import load_promote_config
from mmm.registry.promote import promote
from mmm.registry.versions import EVALUATOR, TOKENIZER
from mmm.tracking import resolve_tracking_uri
from mmm.training.configs import (
    load_evaluator_config,
    load_length_config,
    load_stage1_config,
    load_stage2_config,
)
from mmm.training.evaluator import train_evaluator
from mmm.training.length import train_length
from mmm.training.stage1 import train_stage1
from mmm.training.stage2 import prepare_stage2_data, train_stage2

PIPELINES = {
    "full": [
        "evaluator",
        "promote-evaluator",
        "stage1",
        "promote-tokenizer",
        "tokenize",
        "stage2",
        "length",
        "evaluate",
        "promote-text2motion",
    ],
    "stage1": ["stage1", "promote-tokenizer"],
    "stage2": ["tokenize", "stage2", "length"],
    "evaluate": ["evaluate"],
    "promote": ["promote-evaluator", "promote-tokenizer", "promote-text2motion"],
    "parts": ["stage1-parts", "stage2-parts", "promote-upperbody"],
}


def _common(ctx: Context) -> list[str]:
    """What every step shares: the data and the tracking store (with the user's data.*/logger.* overrides)."""
    cfg: PipelineConfig = ctx.cfg
    return [
        f"data={cfg.data.name}",
        f"data.root={cfg.data.root}",
        f"logger.tracking_uri={cfg.logger.tracking_uri}",
        f"logger.artifact_root={cfg.logger.artifact_root}",
        *ctx.shared_overrides,
    ]


def _data_fingerprint(ctx: Context, extra_parts: tuple[str, ...] = ()) -> str:
    """The content fingerprint of the pipeline's data (features, captions, splits, statistics), with
    `extra_parts` (labels, new_joints) for the steps that read them too."""
    memo = f"data_fingerprint{'+' + '+'.join(extra_parts) if extra_parts else ''}"
    if memo not in ctx.outputs:
        TokenizerDataModule(ctx.cfg.data).prepare_data()  # synthesize the default dataset when missing
        ctx.outputs[memo] = {"value": dataset_fingerprint(ctx.cfg.data.root, extra_parts)}
    return ctx.outputs[memo]["value"]


LABELLED = ("labels", "new_joints")  # what adherence checks read besides the features


def code_key() -> str:
    """The code a step runs: the package's version (the git commit, `+dirty` with changes, or the
    installed version) and, for a dirty checkout, a digest of the changes to src/, so an edit
    between two runs is noticed."""
    version = versions.code_version()  # looked up at call time: tests stand in another version
    if version.endswith("+dirty"):
        root = Path(__file__).resolve().parents[3]
        try:
            diff = subprocess.run(
                ["git", "-C", str(root), "diff", "HEAD", "--", "src"], capture_output=True, timeout=30
            ).stdout
        except (OSError, subprocess.SubprocessError):
            diff = b""
        version += "-" + hashlib.sha256(diff).hexdigest()[:12]
    return version


def _code(ctx: Context) -> str:
    if "code_version" not in ctx.outputs:
        ctx.outputs["code_version"] = {"value": code_key()}
    return ctx.outputs["code_version"]["value"]


def _key(ctx: Context, config: DictConfig, extra_parts: tuple[str, ...] = (), **consumed) -> dict:
    """A step's inputs: its resolved config (hash), the code version, the data's content
    fingerprint and what it consumes from earlier steps."""
    return {
        "config": config_hash(config),
        "code": _code(ctx),
        "data": _data_fingerprint(ctx, extra_parts),
        **consumed,
    }


def _dataset(ctx: Context) -> tuple[str, str, str]:
    """The pipeline's data as the parent run's dataset input: (name, root, fingerprint)."""
    return ctx.cfg.data.name, ctx.cfg.data.root, _data_fingerprint(ctx)


def _champion_version(ctx: Context, name: str):
    """The registered model's current champion version, or None."""
    try:
        return MlflowClient(ctx.tracking_uri).get_model_version_by_alias(name, "champion")
    except MlflowException:
        return None


def _champion(ctx: Context, name: str) -> str | None:
    """'<name> v<version>' of the current champion, or None."""
    version = _champion_version(ctx, name)
    return None if version is None else f"{name} v{version.version}"


def _run_exists(ctx: Context, outputs: dict) -> bool:
    try:
        return MlflowClient(ctx.tracking_uri).get_run(outputs["run_id"]).info.status == "FINISHED"
    except (KeyError, MlflowException):
        return False


def _trained(result) -> dict:
    return {
        "run_id": result.run_id,
        "checkpoint": result.best_checkpoint,
        "metrics": {k: v for k, v in result.metrics.items() if k.startswith(("val/", "test/"))},
    }


def _promoted(name: str, decision) -> dict:
    return {"model": name, "version": decision.version, "alias": decision.alias, "reason": decision.reason}


# -- the steps -------------------------------------------------------------------------------------
# Each step's overrides build both its config (whose resolved hash is part of its key) and its run.
def step_evaluator() -> Step:
    def config(ctx):
        return load_evaluator_config(
            [*_common(ctx), "trainer.enable_progress_bar=false", *ctx.cfg.overrides.evaluator]
        )

    def run(ctx):
        return _trained(train_evaluator(config(ctx)))

    return Step("evaluator", lambda ctx: _key(ctx, config(ctx)), run, _run_exists)


def _promote_step(kind: str, source_step: str | None) -> Step:
    name = PROMOTABLE[kind].registered

    def candidate(ctx):
        return ctx.outputs.get(source_step, {}).get("run_id") if source_step else None

    def config(ctx):
        chosen = candidate(ctx)
        return load_promote_config(
            [*_common(ctx), *([f"candidate={chosen}"] if chosen else []), *ctx.cfg.overrides.promote]
        )

    def inputs(ctx):
        return _key(
            ctx,
            config(ctx),
            LABELLED if kind == "upperbody" else (),
            candidate=candidate(ctx),
            evaluator=_champion(ctx, EVALUATOR) if kind in ("tokenizer", "text2motion") else None,
        )

    def run(ctx):
        return _promoted(name, promote(kind, config(ctx)))

    return Step(f"promote-{kind}", inputs, run, lambda ctx, outputs: _champion(ctx, name) is not None)


def _champion_tokenizer(ctx: Context) -> str | None:
    """'<name> v<version>' of the tokenizer champion when it was measured on the pipeline's data, or
    None: stage 2 then trains on this pipeline's own stage-1 run, so a recipe on other data
    (recipe=quality) keeps its own tokenizer instead of one normalized for another dataset."""
    version = _champion_version(ctx, TOKENIZER)
    if version is None or version.tags.get("data.fingerprint") != _data_fingerprint(ctx):
        return None
    return f"{TOKENIZER} v{version.version}"


def _stage2_options(ctx) -> list[str]:
    tokenizer = (
        f"models:/{TOKENIZER}@champion"
        if _champion_tokenizer(ctx)
        else ctx.outputs.get("stage1", {}).get("run_id")
    )
    return [*_common(ctx), *([f"stage1={tokenizer}"] if tokenizer else [])]


def step_stage1() -> Step:
    def config(ctx):
        return load_stage1_config(
            [*_common(ctx), "trainer.enable_progress_bar=false", *ctx.cfg.overrides.stage1]
        )

    def run(ctx):
        return _trained(train_stage1(config(ctx)))

    return Step("stage1", lambda ctx: _key(ctx, config(ctx)), run, _run_exists)


def step_tokenize() -> Step:
    def config(ctx):
        return load_stage2_config([*_stage2_options(ctx), *ctx.cfg.overrides.stage2])

    def run(ctx):
        dm = prepare_stage2_data(config(ctx))
        return {
            "tokens": str(dm.tokens.folder),
            "motions": len(dm.tokens),
            "captions": len(dm.caption_cache),
            "tokenizer": dm.source.identity,
        }

    return Step(
        "tokenize",
        lambda ctx: _key(
            ctx,
            config(ctx),
            tokenizer=_champion_tokenizer(ctx) or ctx.outputs.get("stage1", {}).get("run_id"),
        ),
        run,
        lambda ctx, outputs: Path(outputs.get("tokens", "")).is_dir(),
    )


def step_stage2() -> Step:
    def config(ctx):
        return load_stage2_config(
            [*_stage2_options(ctx), "trainer.enable_progress_bar=false", *ctx.cfg.overrides.stage2]
        )

    def run(ctx):
        return _trained(train_stage2(config(ctx)))

    return Step(
        "stage2",
        lambda ctx: _key(ctx, config(ctx), tokens=ctx.outputs.get("tokenize", {}).get("tokenizer")),
        run,
        _run_exists,
    )


def step_length() -> Step:
    def config(ctx):
        return load_length_config(
            [*_stage2_options(ctx), "trainer.enable_progress_bar=false", *ctx.cfg.overrides.length]
        )

    def run(ctx):
        return _trained(train_length(config(ctx)))

    return Step(
        "length",
        lambda ctx: _key(ctx, config(ctx), tokens=ctx.outputs.get("tokenize", {}).get("tokenizer")),
        run,
        _run_exists,
    )


def step_evaluate() -> Step:
    def model(ctx):
        return ctx.outputs.get("stage2", {}).get("run_id")

    def config(ctx):
        chosen = model(ctx)
        evaluator = [f"evaluator.reference=models:/{EVALUATOR}@champion"] if _champion(ctx, EVALUATOR) else []
        return load_evaluate_config(
            [
                *_common(ctx),
                *([f"text2motion={chosen}"] if chosen else []),
                *evaluator,
                *ctx.cfg.overrides.evaluate,
            ]
        )

    def run(ctx):
        results = evaluate(config(ctx))
        return {"run_id": results.get("run_id"), "metrics": results["metrics"], "table": results["table"]}

    # Prompt adherence reads labels/ and new_joints/: they are part of its data.
    return Step(
        "evaluate",
        lambda ctx: _key(ctx, config(ctx), LABELLED, model=model(ctx), evaluator=_champion(ctx, EVALUATOR)),
        run,
        _run_exists,
    )


def step_stage1_parts() -> Step:
    def config(ctx):
        return load_stage1_config(
            [*_common(ctx), "trainer.enable_progress_bar=false", *ctx.cfg.overrides.stage1_parts], parts=True
        )

    def run(ctx):
        return _trained(train_stage1(config(ctx)))

    return Step("stage1-parts", lambda ctx: _key(ctx, config(ctx)), run, _run_exists)


def step_stage2_parts() -> Step:
    def tokenizer(ctx):
        return ctx.outputs.get("stage1-parts", {}).get("run_id")

    def config(ctx):
        chosen = tokenizer(ctx)
        return load_stage2_config(
            [
                *_common(ctx),
                *([f"stage1={chosen}"] if chosen else []),
                "trainer.enable_progress_bar=false",
                *ctx.cfg.overrides.stage2_parts,
            ],
            parts=True,
        )

    def run(ctx):
        return _trained(train_stage2(config(ctx)))

    return Step(
        "stage2-parts", lambda ctx: _key(ctx, config(ctx), tokenizer=tokenizer(ctx)), run, _run_exists
    )


STEPS = {
    "evaluator": step_evaluator,
    "promote-evaluator": lambda: _promote_step("evaluator", "evaluator"),
    "stage1": step_stage1,
    "promote-tokenizer": lambda: _promote_step("tokenizer", "stage1"),
    "tokenize": step_tokenize,
    "stage2": step_stage2,
    "length": step_length,
    "evaluate": step_evaluate,
    "promote-text2motion": lambda: _promote_step("text2motion", "stage2"),
    "stage1-parts": step_stage1_parts,
    "stage2-parts": step_stage2_parts,
    "promote-upperbody": lambda: _promote_step("upperbody", "stage2-parts"),
}


def run_pipeline(
    name: str, cfg_node: DictConfig, force: list[str] = (), overrides: list[str] = ()
) -> list[StepReport]:
    if name not in PIPELINES:
        raise ValueError(f"unknown pipeline {name!r}; choose one of {', '.join(PIPELINES)}")
    unknown = set(force) - set(PIPELINES[name]) - {"all"}
    if unknown:
        raise ValueError(
            f"--force {sorted(unknown)}: not steps of pipeline {name!r} ({', '.join(PIPELINES[name])})"
        )
    cfg: PipelineConfig = to_object(cfg_node)
    ctx = Context(cfg, resolve_tracking_uri(cfg.logger.tracking_uri), shared_overrides(list(overrides)))
    steps = [STEPS[s]() for s in PIPELINES[name]]
    forced = set(PIPELINES[name]) if "all" in force else set(force)
    return run_steps(
        name,
        steps,
        ctx,
        Path(cfg.state_file),
        forced,
        artifact_root=cfg.logger.artifact_root,
        dataset=_dataset,
    )

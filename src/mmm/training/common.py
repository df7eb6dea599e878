"""The run machinery the trainers share: trainer, strategy and logger from config, the run
folder (new, or the one a resume continues), MLflow tracking (config, tags, dataset, checkpoints,
system metrics) and `tracked_fit`, which runs a fit as one tracked MLflow run: each trainer only
loads its config, builds its data and module and calls it.

The shared config sections are in mmm.training.configs, the optimizer in mmm.optim, the
checkpoint callbacks and the resume state in mmm.callbacks.checkpoints.
"""

from __future__ import annotations

import logging
import os
import re
import warnings
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Callable

import lightning as L
import torch
from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.strategies import DDPStrategy
from lightning.pytorch.utilities import rank_zero_only
from mlflow.entities import Param
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from mmm.callbacks.checkpoints import RunState, checkpoint_callbacks
from mmm.checkpoints import WEIGHT_EMA_KEY, load_checkpoint
from mmm.config import conf_dir, config_hash
from mmm.device import cpu_has_bf16_matmul
from mmm.kinds import ModelKind
from mmm.resolve import log_artifact_with_digest
from mmm.tracking import (
    DESCRIPTION_TAG,
    TrackingConfig,
    artifact_location,
    log_dataset_input,
    prepare_experiment,
    resolve_tracking_uri,
    source_tags,
    timestamp,
)
from mmm.training.checkpoint_io import AtomicCheckpointIO
from mmm.training.configs import TrainerConfig, check_first_validation
from mmm.training.runs import (
    claim_run_directory,
    discard_unused_run_directory,
    resume_target,
    run_directory,
    shared_run_directory,
)

log = logging.getLogger(__name__)


def build_strategy(cfg: TrainerConfig):
    if cfg.strategy in ("ddp", "ddp_spawn"):
        # The quantizer keeps its buffers identical across ranks itself; broadcasting them
        # from rank 0 at every forward would only hide a bug and cost a copy.
        return DDPStrategy(
            start_method="spawn" if cfg.strategy == "ddp_spawn" else "popen",
            process_group_backend=cfg.process_group_backend,
            broadcast_buffers=False,
            find_unused_parameters=False,
        )
    return cfg.strategy


def build_logger(
    cfg: TrackingConfig, run_id: str | None = None, run_name: str | None = None
) -> MLFlowLogger | None:
    if not cfg.enabled:
        return None
    if rank_zero_only.rank != 0:
        # Only rank 0 logs, and merely opening the store is not free: a fresh SQLite store is
        # created and migrated on first use, which two processes started at once (torchrun, one
        # per node) race on. Other ranks train without a logger (trainer.loggers == []).
        return None
    return MLFlowLogger(
        experiment_name=cfg.experiment,
        run_name=cfg.run_name or run_name,
        tracking_uri=resolve_tracking_uri(cfg.tracking_uri),
        artifact_location=artifact_location(cfg.tracking_uri, cfg.artifact_root),
        run_id=run_id,
    )


def training_precision(precision: str, accelerator: str) -> str:
    """Lightning's precision for `trainer.precision`: `auto` is bf16-mixed where the device has
    bfloat16 kernels (a CPU with AVX-512 BF16 or AMX, a GPU that supports bfloat16) and 32-true
    elsewhere, where the autocast would emulate every matmul; any other name is kept."""
    if precision != "auto":
        return precision
    on_gpu = accelerator in ("gpu", "cuda") or (accelerator == "auto" and torch.cuda.is_available())
    fast = torch.cuda.is_available() and torch.cuda.is_bf16_supported() if on_gpu else cpu_has_bf16_matmul()
    chosen = "bf16-mixed" if fast else "32-true"
    log.info("trainer.precision=auto: %s (bfloat16 kernels on this %s: %s)", chosen, accelerator, fast)
    return chosen


# What Lightning prints on every fit that concerns none of this package's runs: an advert for its
# cloud logger (when the Trainer is built), the model summary's note that it sizes bfloat16 weights
# as float32, and torch's deprecation of a class Lightning's own pytree helper still builds.
LIGHTNING_NOISE_WARNINGS = (
    "Precision bf16-mixed is not supported by the model summary",
    "`isinstance(treespec, LeafSpec)` is deprecated",
)
LIGHTNING_ADVERT = "💡 Tip:"


class _NoAdvert(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(LIGHTNING_ADVERT)


@contextmanager
def quiet_lightning():
    """Build and fit a Trainer without `LIGHTNING_NOISE_WARNINGS` and the advert; every other
    warning and log line is shown as before, and the filters are gone afterwards."""
    rank_zero_log = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    no_advert = _NoAdvert()
    rank_zero_log.addFilter(no_advert)
    try:
        with warnings.catch_warnings():
            for message in LIGHTNING_NOISE_WARNINGS:
                warnings.filterwarnings("ignore", message=re.escape(message))
            yield
    finally:
        rank_zero_log.removeFilter(no_advert)


def build_trainer(cfg: TrainerConfig, callbacks: list, logger, default_root_dir: str) -> L.Trainer:
    precision = training_precision(str(cfg.precision), cfg.accelerator)
    if cfg.accelerator == "cpu" and precision.startswith("bf16") and cpu_has_bf16_matmul() is False:
        # Without oneDNN's bfloat16 kernels the autocast emulates each matmul: slower than float32.
        log.warning(
            "trainer.precision=%s on a CPU without bfloat16 kernels (AVX-512 or newer) trains "
            "slower than float32; set trainer.precision=32-true (or auto)",
            precision,
        )
    return L.Trainer(
        accelerator=cfg.accelerator,
        devices=cfg.devices,
        num_nodes=cfg.num_nodes,
        strategy=build_strategy(cfg),
        precision=precision,
        max_steps=cfg.max_steps,
        val_check_interval=cfg.val_check_interval,
        check_val_every_n_epoch=None,  # validate every val_check_interval steps across epochs
        limit_val_batches=cfg.limit_val_batches,
        log_every_n_steps=cfg.log_every_n_steps,
        gradient_clip_val=cfg.gradient_clip_val,
        num_sanity_val_steps=cfg.num_sanity_val_steps,
        enable_progress_bar=cfg.enable_progress_bar,
        deterministic=cfg.deterministic,
        callbacks=callbacks,
        logger=logger if logger is not None else False,
        default_root_dir=default_root_dir,
        use_distributed_sampler=False,  # our loaders shard by rank and resume themselves
        plugins=[
            AtomicCheckpointIO()
        ],  # a save never leaves a partial last.ckpt/best.ckpt (see checkpoint_io.py)
    )


def read_checkpoint_meta(path: str | Path) -> dict:
    """The few fields a resume needs, read with weights_only=True (no code runs on load); a file
    that is not an intact checkpoint of this package is a CheckpointError naming it."""
    ckpt = load_checkpoint(path, None)
    return {
        "mlflow_run_id": ckpt.get("mlflow_run_id"),
        "global_step": ckpt.get("global_step"),
        "hyper_parameters": ckpt.get("hyper_parameters"),
        "weight_ema": ckpt.get(WEIGHT_EMA_KEY),
    }


def resumable_run_id(run_id: str | None, cfg: TrackingConfig) -> str | None:
    """The MLflow run a resumed training goes on logging to: the checkpoint's, when this store has
    it (a checkpoint from another store starts a new run, said so)."""
    if not run_id or not cfg.enabled:
        return run_id
    uri = resolve_tracking_uri(cfg.tracking_uri)
    try:
        MlflowClient(uri).get_run(run_id)
        return run_id
    except MlflowException:
        log.warning(
            "the checkpoint's MLflow run %s is not in %s: the resumed training logs to a new run", run_id, uri
        )
        return None


def flatten_config(cfg: DictConfig, exclude: tuple[str, ...] = ()) -> dict[str, str]:
    """Dotted key -> value string of a resolved config, for MLflow params; keys in `exclude`
    (dotted prefixes) are left out."""
    out: dict[str, str] = {}

    def walk(node, prefix: str) -> None:
        if prefix and any(prefix == e or prefix.startswith(e + ".") for e in exclude):
            return
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}.{k}" if prefix else str(k))
        else:
            out[prefix] = str(node)[:500]

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return out


@rank_zero_only
def log_config(
    logger: MLFlowLogger | None, cfg: DictConfig, resumed: bool, exclude: tuple[str, ...] = ()
) -> None:
    """The resolved config as params (once, one spelling: the modules' own hyper-parameters are not
    logged) and config.yaml; `exclude`: what this command does not use."""
    if logger is None:
        return
    if not resumed:  # MLflow params are immutable: a resumed run keeps those it was started with
        params = flatten_config(cfg, exclude)
        client, run_id = logger.experiment, logger.run_id
        items = [Param(k, v) for k, v in params.items()]
        for i in range(0, len(items), 100):  # the store's batch limit
            client.log_batch(run_id, params=items[i : i + 100])
        client.set_tag(run_id, "config.hash", config_hash(cfg))
    logger.experiment.log_text(logger.run_id, OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")


@rank_zero_only
def tag_run(logger: MLFlowLogger | None, tags: dict[str, object]) -> None:
    if logger is not None:
        for key, value in tags.items():
            logger.experiment.set_tag(logger.run_id, key, "" if value is None else str(value))


@rank_zero_only
def log_checkpoints(
    logger: MLFlowLogger | None, best: ModelCheckpoint, last: ModelCheckpoint
) -> dict[str, str]:
    """Upload best.ckpt and last.ckpt to the run's `checkpoints/` artifacts, each with its sha256
    as a run tag (what the download cache keys by: a resumed run uploads new files under the same
    names); returns their paths."""
    paths = {name: cb.best_model_path for name, cb in (("best", best), ("last", last)) if cb.best_model_path}
    if logger is not None:
        for path in paths.values():
            if os.path.exists(path):
                log_artifact_with_digest(logger.experiment, logger.run_id, path, "checkpoints")
    return paths


def model_label(model_cfg) -> str:
    """`tiny`, `paper` or `custom`: which conf/model file the sizes are."""
    ours = asdict(model_cfg) if is_dataclass(model_cfg) else dict(model_cfg)
    for path in sorted((conf_dir() / "model").glob("*.yaml")):
        known = OmegaConf.to_container(OmegaConf.load(path))
        if all(
            ours.get(part, {}) | dict(values) == ours.get(part, {})
            for part, values in known.items()
            if isinstance(values, dict)
        ):
            return path.stem
    return "custom"


def run_name(kind: str, data_name: str, model_cfg=None) -> str:
    """`<kind>-<sizes>-<data>-<time>`, e.g. stage1-tiny-synthetic-20261123-201500 (no sizes for
    the length estimator and the evaluator)."""
    parts = [kind] + ([model_label(model_cfg)] if model_cfg is not None else []) + [data_name, timestamp()]
    return "-".join(parts)


@dataclass
class TrackedRun:
    """What a trainer tells `tracked_fit` about its run besides the module and the data."""

    kind: ModelKind  # what it trains (mmm.kinds.KINDS): names the run, tags it `mmm.stage`
    cfg_node: DictConfig  # the resolved config, logged as params and config.yaml
    exclude: tuple[str, ...] = ()  # config keys this command does not use (not logged)
    tags: dict = field(default_factory=dict)
    dataset: tuple[str, str, str] | None = None  # (name, root, fingerprint): the MLflow dataset input
    description: str = ""  # markdown shown on the run's page (links to what it was made from)
    model_cfg: object = None  # the sizes, for the run name
    metrics: dict[str, float] = field(default_factory=dict)  # logged at step 0 (baselines)


@dataclass
class TrainResult:
    run_id: str | None
    checkpoint_dir: str
    best_checkpoint: str | None
    last_checkpoint: str | None
    metrics: dict[str, float] = field(default_factory=dict)
    stopped_early: bool = False


@dataclass
class RunTarget:
    """Where a fit writes and what it continues: the run folder, and for a resume the checkpoint
    and the MLflow run it goes on logging to."""

    run_dir: Path
    ckpt_path: Path | None = None
    run_id: str | None = None


def check_schedule(trainer: TrainerConfig) -> None:
    """Checkpoints are written at validations: refuse a fit that ends before its first one (it
    would finish with no model), and warn when its last steps come after the last one."""
    steps, every = trainer.max_steps, trainer.val_check_interval
    check_first_validation(steps, every)
    if steps % every:
        log.warning(
            "the last %d of the fit's %d steps come after its last validation (step %d): no checkpoint "
            "holds them; make trainer.max_steps a multiple of trainer.val_check_interval=%d to keep them",
            steps % every,
            steps,
            steps - steps % every,
            every,
        )


def run_target(
    cfg, resume: str | None = None, check: Callable[[Path, dict], None] | None = None
) -> RunTarget:
    """A new run folder under `cfg.output_dir`, or with `resume` ("last" or a checkpoint path) the
    checkpoint to continue and the folder it continues in (`resume_target`); `check(checkpoint,
    meta)` (meta: `read_checkpoint_meta`'s, read once here) refuses a resume that would silently
    change the run (raises) before anything is written."""
    check_schedule(cfg.trainer)
    if not resume:
        return RunTarget(run_directory(cfg.output_dir))
    ckpt_path, run_dir = resume_target(resume, cfg.output_dir)
    meta = read_checkpoint_meta(ckpt_path)
    if check is not None:
        check(ckpt_path, meta)
    run_id = resumable_run_id(meta["mlflow_run_id"], cfg.logger)
    log.info("resuming %s in %s (MLflow run %s)", ckpt_path, run_dir, run_id)
    return RunTarget(run_dir, ckpt_path, run_id)


def tracked_fit(
    run: TrackedRun,
    cfg,
    module: L.LightningModule,
    target: RunTarget,
    callbacks: list,
    *,
    datamodule=None,
    loaders: dict | None = None,
    result_type: type = TrainResult,
    **fields,
):
    """Fit `module` as one MLflow run in `target` (see `run_target`) and return (result, trainer, logger).

    The run folder is claimed for the fit (`claim_run_directory`: no other training writes into
    it meanwhile). The run is named for what it is (`run_name`, unless logger.run_name is set),
    tagged with the model kind, the git commit and `run.tags`, records its dataset as an input and
    the resolved config once; best.ckpt/last.ckpt are written to <run folder>/checkpoints (and
    uploaded at the end), the learning rate is charted (`train/lr`) and MLflow samples system
    metrics while it trains. A target with a checkpoint resumes it (and its MLflow run). Only
    rank 0 writes to MLflow. `result_type` may add `fields` to the TrainResult.
    """
    created = not target.run_dir.exists()
    lock = claim_run_directory(target.run_dir, resuming=target.ckpt_path is not None)
    try:
        with quiet_lightning():
            return _fit(run, cfg, module, target, callbacks, datamodule, loaders, result_type, fields)
    except BaseException:
        if lock is not None and created:  # e.g. a refused resume: no empty run folder left behind
            lock.release()
            lock = None
            discard_unused_run_directory(target.run_dir)
        raise
    finally:
        if lock is not None:
            lock.release()


def _fit(
    run: TrackedRun,
    cfg,
    module: L.LightningModule,
    target: RunTarget,
    callbacks: list,
    datamodule,
    loaders: dict | None,
    result_type: type,
    fields: dict,
):
    run_dir, ckpt_path, run_id = target.run_dir, target.ckpt_path, target.run_id
    kind = run.kind.name
    data_name = run.dataset[0] if run.dataset else cfg.data.name
    logger = build_logger(cfg.logger, run_id=run_id, run_name=run_name(kind, data_name, run.model_cfg))
    best, last = checkpoint_callbacks(run_dir / "checkpoints", cfg.callbacks.checkpoint)
    run_state = RunState(
        getattr(getattr(cfg, "data", None), "batch_size", None), cfg.trainer.resume_restart_epoch
    )
    if logger is not None:
        callbacks = [*callbacks, LearningRateMonitor(logging_interval="step")]
    trainer = build_trainer(cfg.trainer, [best, last, run_state, *callbacks], logger, str(run_dir))
    if ckpt_path:  # refuse a resume that would silently change the run before the MLflow run is touched
        run_state.check_resume(trainer, module, torch.load(ckpt_path, map_location="cpu", weights_only=True))
    monitor = None
    if logger is not None:
        uri = resolve_tracking_uri(cfg.logger.tracking_uri)
        if rank_zero_only.rank == 0:
            prepare_experiment(
                MlflowClient(uri), cfg.logger.experiment, artifact_location(uri, cfg.logger.artifact_root)
            )
        _ = logger.experiment  # create the run now, before any process is spawned
        log_config(logger, run.cfg_node, resumed=run_id is not None, exclude=run.exclude)
        tag_run(
            logger,
            {
                "mmm.stage": kind,
                **source_tags(f"mmm train {kind}"),
                **run.tags,
                **({DESCRIPTION_TAG: run.description} if run.description else {}),
            },
        )
        if rank_zero_only.rank == 0:
            if run.dataset and run_id is None:
                log_dataset_input(logger.experiment, logger.run_id, *run.dataset)
            if run.metrics:
                logger.log_metrics(run.metrics, step=0)
            monitor = _system_metrics(logger.run_id, uri, resumed=run_id is not None)
    try:
        with shared_run_directory(run_dir):
            trainer.fit(
                module,
                datamodule=datamodule,
                ckpt_path=str(ckpt_path) if ckpt_path else None,
                weights_only=True,
                **(loaders or {}),
            )
    finally:
        if monitor is not None:
            monitor.finish()
    result = train_result(
        trainer,
        logger,
        cfg.logger.log_checkpoints,
        best,
        last,
        run_dir,
        cfg.trainer.max_steps,
        result_type=result_type,
        **fields,
    )
    return result, trainer, logger


def text_record(text_encoder, cfg) -> dict:
    """The frozen text encoder a model reads the sentence embeddings of (`cfg`: its TextConfig),
    as the model's checkpoint records it."""
    return {"name": text_encoder.name, "identity": text_encoder.identity, **cfg.options()}


def log_final_metrics(
    result: TrainResult, trainer: L.Trainer, logger: MLFlowLogger | None, metrics: dict[str, float]
) -> None:
    """What a trainer measures after the fit (test scores, timings): into the result, and logged
    to the run at its last step (rank 0)."""
    result.metrics.update(metrics)
    if logger is not None and trainer.is_global_zero:
        logger.log_metrics(metrics, step=trainer.global_step)


def _system_metrics(run_id: str, tracking_uri: str, resumed: bool):
    """MLflow's CPU/memory/disk/network (and GPU) sampler for the run (`system/*` charts), or None
    where it cannot run (no psutil)."""
    try:
        # Imported here: it needs psutil, which an install may lack (then there is no chart, not an error).
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        monitor = SystemMetricsMonitor(
            run_id,
            sampling_interval=5,
            samples_before_logging=1,
            resume_logging=resumed,
            tracking_uri=tracking_uri,
        )
        monitor.start()
        return monitor
    except Exception as e:  # pragma: no cover - an optional chart, never a reason to stop training
        log.warning("system metrics not recorded: %s", e)
        return None


def train_result(
    trainer: L.Trainer,
    logger: MLFlowLogger | None,
    log_to_mlflow: bool,
    best: ModelCheckpoint,
    last: ModelCheckpoint,
    run_dir: Path,
    max_steps: int,
    extra_metrics: dict[str, float] | None = None,
    result_type: type = TrainResult,
    **fields,
):
    """After fit: upload best/last checkpoints to the run (rank 0, when `log_to_mlflow`) and
    collect what the caller gets back (`result_type` may add `fields`)."""
    paths = (log_checkpoints(logger, best, last) if log_to_mlflow else None) or {}
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
    return result_type(
        run_id=logger.run_id if logger is not None else None,
        checkpoint_dir=str(run_dir / "checkpoints"),
        best_checkpoint=paths.get("best") or best.best_model_path or None,
        last_checkpoint=paths.get("last") or last.best_model_path or None,
        metrics={**metrics, **(extra_metrics or {})},
        stopped_early=trainer.global_step < max_steps,
        **fields,
    )

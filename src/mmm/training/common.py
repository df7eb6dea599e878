"""What the trainers share: trainer and strategy from config, MLflow tracking, checkpoints, resume,
and `tracked_fit`, which runs a fit as one tracked MLflow run (each trainer only builds its data
and module)."""

from __future__ import annotations

import logging
import os
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.strategies import DDPStrategy
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from mmm.tokenizer.network import TokenizerConfig
from mmm.tracking import TrackingConfig, artifact_location, resolve_tracking_uri
from mmm.training.checkpoint_io import AtomicCheckpointIO
from mmm.training.runs import shared_run_directory
from mmm.transformer.network import TransformerConfig

log = logging.getLogger(__name__)


@dataclass
class ModelConfig:
    """Sizes of both stages (conf/model/tiny.yaml, paper.yaml): `model=paper` sizes both."""

    tokenizer: TokenizerConfig = field(default_factory=TokenizerConfig)
    transformer: TransformerConfig = field(default_factory=TransformerConfig)


@dataclass
class TrainerConfig:
    accelerator: str = "cpu"  # cpu | gpu | auto
    devices: Any = 1  # count, list of ids, or "auto"
    num_nodes: int = 1
    strategy: str = "auto"  # auto | ddp | ddp_spawn (ddp strategies use the codebook-safe settings)
    process_group_backend: str | None = None  # gloo on CPU, nccl on GPUs by default
    precision: str = "32-true"
    max_steps: int = 2000
    val_check_interval: int = 500  # optimizer steps between validations
    limit_val_batches: float = 1.0
    log_every_n_steps: int = 10
    gradient_clip_val: float | None = None
    num_sanity_val_steps: int = 0
    enable_progress_bar: bool = True
    deterministic: bool = False
    # A resume continues mid-epoch at the batch it stopped at, which is only the same data position
    # with the same batch size and number of processes; true: start the interrupted epoch over instead.
    resume_restart_epoch: bool = False


@dataclass
class CheckpointConfig:
    monitor: str = "val/mpjpe_root_aligned_mm"
    mode: str = "min"


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


def build_logger(cfg: TrackingConfig, run_id: str | None = None, run_name: str | None = None) -> MLFlowLogger | None:
    if not cfg.enabled:
        return None
    return MLFlowLogger(
        experiment_name=cfg.experiment,
        run_name=cfg.run_name or run_name,
        tracking_uri=resolve_tracking_uri(cfg.tracking_uri),
        artifact_location=artifact_location(cfg.tracking_uri, cfg.artifact_root),
        run_id=run_id,
    )


def build_trainer(cfg: TrainerConfig, callbacks: list, logger, default_root_dir: str) -> L.Trainer:
    return L.Trainer(
        accelerator=cfg.accelerator,
        devices=cfg.devices,
        num_nodes=cfg.num_nodes,
        strategy=build_strategy(cfg),
        precision=cfg.precision,
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
        plugins=[AtomicCheckpointIO()],  # a save never leaves a partial last.ckpt/best.ckpt (see checkpoint_io.py)
    )


def checkpoint_callbacks(directory: Path, cfg: CheckpointConfig) -> tuple[ModelCheckpoint, ModelCheckpoint]:
    """best.ckpt (by the monitored metric) and last.ckpt (at every validation), overwritten in
    place when a run resumes (no last-v1.ckpt)."""
    best = ModelCheckpoint(
        dirpath=directory, filename="best", monitor=cfg.monitor, mode=cfg.mode, save_top_k=1,
        auto_insert_metric_name=False, enable_version_counter=False,
    )
    last = ModelCheckpoint(dirpath=directory, filename="last", monitor=None, save_top_k=1, enable_version_counter=False)
    return best, last


# Optimizer settings the restored optimizer state would silently override (warmup, milestones and
# gamma take effect: the schedule is rebuilt from the config).
RESTORED_OPTIM_KEYS = ("lr", "betas", "weight_decay")


class RunState(L.Callback):
    """Keeps in every checkpoint what Lightning does not: the MLflow run id (a resumed run goes on
    logging to the same run), the random generators' states (it goes on drawing the same
    numbers) and the data position's meaning (batch size, world size), in types that load with
    weights_only=True. On resume it refuses what would silently change the run: another batch
    size or world size (unless `restart_epoch`), or optimizer settings the restored optimizer
    state would override."""

    def __init__(self, batch_size: int | None = None, restart_epoch: bool = False):
        self.batch_size, self.restart_epoch = batch_size, restart_epoch

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        for logger in trainer.loggers:
            if isinstance(logger, MLFlowLogger):
                checkpoint["mlflow_run_id"] = logger.run_id
        np_state = np.random.get_state()
        checkpoint["rng"] = {
            "torch": torch.get_rng_state(),
            "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), int(np_state[2]), int(np_state[3]), float(np_state[4])],
            "python": random.getstate(),
        }
        checkpoint["data_position"] = {"batch_size": self.batch_size, "world_size": trainer.world_size}
        # The weights' own fingerprint: every load checks it (mmm.checkpoints.load_checkpoint).
        from mmm.checkpoints import FINGERPRINT_KEY
        from mmm.fingerprint import tensors_fingerprint

        checkpoint[FINGERPRINT_KEY] = tensors_fingerprint(checkpoint.get("state_dict") or {})

    def check_resume(self, trainer, pl_module, checkpoint: dict) -> None:
        """Raise ValueError when resuming `checkpoint` would silently change the run (see the class)."""
        self._check_optimizer(pl_module, checkpoint)
        self._check_data_position(trainer, checkpoint)

    def on_load_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        self.check_resume(trainer, pl_module, checkpoint)
        rng = checkpoint.get("rng")
        if rng is None:
            return
        torch.set_rng_state(rng["torch"])
        name, keys, pos, has_gauss, cached = rng["numpy"]
        np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
        version, state, gauss = rng["python"]
        random.setstate((version, tuple(state), gauss))

    @staticmethod
    def _check_optimizer(pl_module, checkpoint: dict) -> None:
        saved = (checkpoint.get("hyper_parameters") or {}).get("optim") or {}
        ours = (getattr(pl_module, "hparams", None) or {}).get("optim") or {}
        changed = [f"optim.{k}: {saved[k]} in the checkpoint, {ours[k]} now" for k in RESTORED_OPTIM_KEYS
                   if k in saved and k in ours and list(np.atleast_1d(saved[k])) != list(np.atleast_1d(ours[k]))]
        if changed:
            raise ValueError(
                f"cannot resume with changed optimizer settings ({'; '.join(changed)}): the checkpoint's optimizer state would override "
                "them silently; resume with the checkpoint's values, or start a new run (without --resume) to train with new ones"
            )

    def _check_data_position(self, trainer, checkpoint: dict) -> None:
        saved = checkpoint.get("data_position")
        if not saved:
            return  # a checkpoint from before the data position was recorded
        now = {"batch_size": self.batch_size, "world_size": trainer.world_size}
        changed = [f"{k} {saved[k]} in the checkpoint, {now[k]} now" for k in ("batch_size", "world_size")
                   if saved.get(k) is not None and now[k] is not None and saved[k] != now[k]]
        if not changed:
            return
        if not self.restart_epoch:
            raise ValueError(
                f"cannot resume mid-epoch with a changed {' and '.join(c.split(' ')[0] for c in changed)} ({'; '.join(changed)}): the "
                "position in the epoch would point at other batches; resume with the same data.batch_size and devices/num_nodes, or "
                "add trainer.resume_restart_epoch=true to start the interrupted epoch over"
            )
        fit_state = checkpoint.get("loops", {}).get("fit_loop", {}).get("state_dict", {})
        for loader_state in fit_state.get("combined_loader", []):
            if isinstance(loader_state, dict) and "batches" in loader_state:
                loader_state["batches"] = 0  # the epoch restarts at its first batch
        log.warning("resuming with %s: trainer.resume_restart_epoch=true, the interrupted epoch starts over", "; ".join(changed))


def read_checkpoint_meta(path: str | Path) -> dict:
    """The few fields a resume needs, read with weights_only=True (no code runs on load); a file
    that is not an intact checkpoint of this package is a CheckpointError naming it."""
    from mmm.checkpoints import load_checkpoint

    ckpt = load_checkpoint(path, None)
    return {"mlflow_run_id": ckpt.get("mlflow_run_id"), "global_step": ckpt.get("global_step"), "hyper_parameters": ckpt.get("hyper_parameters")}


def resumable_run_id(run_id: str | None, cfg: TrackingConfig) -> str | None:
    """The MLflow run a resumed training goes on logging to: the checkpoint's, when this store has
    it (a checkpoint from another store starts a new run, said so)."""
    if not run_id or not cfg.enabled:
        return run_id
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    uri = resolve_tracking_uri(cfg.tracking_uri)
    try:
        MlflowClient(uri).get_run(run_id)
        return run_id
    except MlflowException:
        log.warning("the checkpoint's MLflow run %s is not in %s: the resumed training logs to a new run", run_id, uri)
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
def log_config(logger: MLFlowLogger | None, cfg: DictConfig, resumed: bool, exclude: tuple[str, ...] = ()) -> None:
    """The resolved config as params (once, one spelling: the modules' own hyper-parameters are not
    logged) and config.yaml; `exclude`: what this command does not use."""
    if logger is None:
        return
    from mmm.config import config_hash

    if not resumed:  # MLflow params are immutable: a resumed run keeps those it was started with
        params = flatten_config(cfg, exclude)
        client, run_id = logger.experiment, logger.run_id
        from mlflow.entities import Param

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
def log_checkpoints(logger: MLFlowLogger | None, best: ModelCheckpoint, last: ModelCheckpoint) -> dict[str, str]:
    """Upload best.ckpt and last.ckpt to the run's `checkpoints/` artifacts, each with its sha256
    as a run tag (what the download cache keys by: a resumed run uploads new files under the same
    names); returns their paths."""
    from mmm.resolve import log_artifact_with_digest

    paths = {name: cb.best_model_path for name, cb in (("best", best), ("last", last)) if cb.best_model_path}
    if logger is not None:
        for path in paths.values():
            if os.path.exists(path):
                log_artifact_with_digest(logger.experiment, logger.run_id, path, "checkpoints")
    return paths


def model_label(model_cfg) -> str:
    """`tiny`, `paper` or `custom`: which conf/model file the sizes are."""
    from dataclasses import asdict, is_dataclass

    from mmm.config import conf_dir

    ours = asdict(model_cfg) if is_dataclass(model_cfg) else dict(model_cfg)
    for path in sorted((conf_dir() / "model").glob("*.yaml")):
        known = OmegaConf.to_container(OmegaConf.load(path))
        if all(ours.get(part, {}) | dict(values) == ours.get(part, {}) for part, values in known.items() if isinstance(values, dict)):
            return path.stem
    return "custom"


def run_name(kind: str, data_name: str, model_cfg=None) -> str:
    """`<kind>-<sizes>-<data>-<time>`, e.g. stage1-tiny-synthetic-20261123-201500 (no sizes for
    the length estimator and the evaluator)."""
    from mmm.tracking import timestamp

    parts = [kind] + ([model_label(model_cfg)] if model_cfg is not None else []) + [data_name, timestamp()]
    return "-".join(parts)


@dataclass
class TrackedRun:
    """What a trainer tells `tracked_fit` about its run besides the module and the data."""

    kind: str  # stage1 | stage1-parts | stage2 | stage2-parts | length | evaluator
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


def tracked_fit(run: TrackedRun, cfg, module: L.LightningModule, run_dir: Path, callbacks: list, *, datamodule=None,
                loaders: dict | None = None, ckpt_path: Path | None = None, run_id: str | None = None, result_type: type = TrainResult, **fields):
    """Fit `module` as one MLflow run and return (result, trainer, logger).

    The run is named for what it is (`run_name`, unless logger.run_name is set), tagged with the
    stage, the git commit and `run.tags`, records its dataset as an input and the resolved config
    once; best.ckpt/last.ckpt are written to run_dir/checkpoints (and uploaded at the end), the
    learning rate is charted (`train/lr`) and MLflow samples system metrics while it trains.
    `run_id`/`ckpt_path` resume a run. Only rank 0 writes to MLflow.
    """
    from lightning.pytorch.callbacks import LearningRateMonitor

    from mmm.tracking import DESCRIPTION_TAG, log_dataset_input, prepare_experiment, source_tags

    data_name = run.dataset[0] if run.dataset else cfg.data.name
    logger = build_logger(cfg.logger, run_id=run_id, run_name=run_name(run.kind, data_name, run.model_cfg))
    best, last = checkpoint_callbacks(run_dir / "checkpoints", cfg.callbacks.checkpoint)
    run_state = RunState(getattr(getattr(cfg, "data", None), "batch_size", None), cfg.trainer.resume_restart_epoch)
    if logger is not None:
        callbacks = [*callbacks, LearningRateMonitor(logging_interval="step")]
    trainer = build_trainer(cfg.trainer, [best, last, run_state, *callbacks], logger, str(run_dir))
    if ckpt_path:  # refuse a resume that would silently change the run before the MLflow run is touched
        run_state.check_resume(trainer, module, torch.load(ckpt_path, map_location="cpu", weights_only=True))
    monitor = None
    if logger is not None:
        uri = resolve_tracking_uri(cfg.logger.tracking_uri)
        if rank_zero_only.rank == 0:
            from mlflow.tracking import MlflowClient

            prepare_experiment(MlflowClient(uri), cfg.logger.experiment, artifact_location(uri, cfg.logger.artifact_root))
        _ = logger.experiment  # create the run now, before any process is spawned
        log_config(logger, run.cfg_node, resumed=run_id is not None, exclude=run.exclude)
        tag_run(logger, {"mmm.stage": run.kind, **source_tags(f"mmm train {run.kind}"), **run.tags,
                         **({DESCRIPTION_TAG: run.description} if run.description else {})})
        if rank_zero_only.rank == 0:
            if run.dataset and run_id is None:
                log_dataset_input(logger.experiment, logger.run_id, *run.dataset)
            if run.metrics:
                logger.log_metrics(run.metrics, step=0)
            monitor = _system_metrics(logger.run_id, uri, resumed=run_id is not None)
    try:
        with shared_run_directory(run_dir):
            trainer.fit(module, datamodule=datamodule, ckpt_path=str(ckpt_path) if ckpt_path else None, weights_only=True, **(loaders or {}))
    finally:
        if monitor is not None:
            monitor.finish()
    result = train_result(trainer, logger, cfg.logger.log_checkpoints, best, last, run_dir, cfg.trainer.max_steps, result_type=result_type, **fields)
    return result, trainer, logger


def _system_metrics(run_id: str, tracking_uri: str, resumed: bool):
    """MLflow's CPU/memory/disk/network (and GPU) sampler for the run (`system/*` charts), or None
    where it cannot run (no psutil)."""
    try:
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        monitor = SystemMetricsMonitor(run_id, sampling_interval=5, samples_before_logging=1, resume_logging=resumed, tracking_uri=tracking_uri)
        monitor.start()
        return monitor
    except Exception as e:  # pragma: no cover - an optional chart, never a reason to stop training
        log.warning("system metrics not recorded: %s", e)
        return None


def train_result(trainer: L.Trainer, logger: MLFlowLogger | None, log_to_mlflow: bool, best: ModelCheckpoint, last: ModelCheckpoint,
                 run_dir: Path, max_steps: int, extra_metrics: dict[str, float] | None = None, result_type: type = TrainResult, **fields):
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

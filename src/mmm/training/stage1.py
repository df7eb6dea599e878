"""Stage 1: train the motion tokenizer (`mmm train stage1 [key=value ...] [--resume last|PATH]`)."""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import lightning as L
from omegaconf import DictConfig

from mmm.callbacks.codebook import CodebookReset, CollapseMonitor
from mmm.callbacks.previews import CodebookUsagePlot, ReconstructionPreview
from mmm.config import compose, to_object
from mmm.data.datamodule import DataConfig, TokenizerDataModule
from mmm.data.normalization import NormalizationConfig
from mmm.tokenizer.module import OptimConfig, TokenizerLossConfig, TokenizerModule
from mmm.training.common import (
    CheckpointConfig, ModelConfig, TrackedRun, TrackingConfig, TrainerConfig, TrainResult, read_checkpoint_meta, resumable_run_id, tracked_fit,
)
from mmm.training.runs import claim_run_directory, resume_target, run_directory

log = logging.getLogger(__name__)


@dataclass
class CollapseConfig:
    action: str = "warn"  # warn | stop | fail
    warmup_steps: int = 200
    window_steps: int = 50
    min_active_fraction: float = 0.02
    perplexity_drop: float = 0.2
    smoothing: float = 0.9
    patience: int = 3


@dataclass
class Stage1Callbacks:
    reset_every_n_steps: int = 20  # 0 disables codebook reset
    collapse: CollapseConfig = field(default_factory=CollapseConfig)
    preview_clips: int = 3  # validation clips rendered at each validation (0: none)
    usage_plot: bool = True
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


@dataclass
class Stage1Config:
    seed: int = 0
    output_dir: str = "outputs/stage1"
    data: DataConfig = field(default_factory=DataConfig)
    normalization: NormalizationConfig = field(default_factory=NormalizationConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    loss: TokenizerLossConfig = field(default_factory=TokenizerLossConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    logger: TrackingConfig = field(default_factory=TrackingConfig)
    callbacks: Stage1Callbacks = field(default_factory=Stage1Callbacks)


def load_stage1_config(overrides: list[str] = (), parts: bool = False) -> DictConfig:
    """conf/train_stage1.yaml, or with parts=True conf/train_stage1_parts.yaml (the part-aware tokenizer)."""
    return compose("train_stage1_parts" if parts else "train_stage1", list(overrides), schema=Stage1Config)


def build_callbacks(cfg: Stage1Config) -> list[L.Callback]:
    cb = cfg.callbacks
    callbacks: list[L.Callback] = [CodebookReset(cb.reset_every_n_steps), CollapseMonitor(**asdict(cb.collapse))]
    if cb.preview_clips > 0:
        callbacks.append(ReconstructionPreview(cb.preview_clips))
    if cb.usage_plot:
        callbacks.append(CodebookUsagePlot())
    return callbacks


def train_stage1(cfg_node: DictConfig, resume: str | None = None) -> TrainResult:
    """Train a tokenizer as configured; `resume` = "last" or a checkpoint path continues a run
    (a checkpoint outside this stage's run folders is only read: the run goes on in a new folder)."""
    cfg: Stage1Config = to_object(cfg_node)
    L.seed_everything(cfg.seed, workers=True)
    ckpt_path, run_id = None, None
    if resume:
        ckpt_path, run_dir = resume_target(resume, cfg.output_dir)
        run_id = resumable_run_id(read_checkpoint_meta(ckpt_path)["mlflow_run_id"], cfg.logger)
        log.info("resuming %s in %s (MLflow run %s)", ckpt_path, run_dir, run_id)
    else:
        run_dir = run_directory(cfg.output_dir)
    lock = claim_run_directory(run_dir, resuming=ckpt_path is not None)
    try:
        return _fit_stage1(cfg, cfg_node, run_dir, ckpt_path, run_id)
    finally:
        if lock is not None:
            lock.release()


def _fit_stage1(cfg: Stage1Config, cfg_node: DictConfig, run_dir: Path, ckpt_path: Path | None, run_id: str | None) -> TrainResult:
    from mmm.fingerprint import dataset_fingerprint

    datamodule = TokenizerDataModule(cfg.data, seed=cfg.seed, normalization=cfg.normalization)
    datamodule.prepare_data()
    datamodule.setup("fit")
    module = TokenizerModule(cfg.data.feature_dim, cfg.model.tokenizer, cfg.optim, cfg.loss, datamodule.mean, datamodule.std)
    fingerprint = dataset_fingerprint(cfg.data.root)
    kind = "stage1-parts" if cfg.model.tokenizer.part_aware else "stage1"
    run = TrackedRun(
        kind, cfg_node, exclude=("model.transformer",), model_cfg=cfg.model,
        tags={"data.name": cfg.data.name, "data.root": cfg.data.root, "data.fingerprint": fingerprint},
        dataset=(cfg.data.name, cfg.data.root, fingerprint),
        description=f"Tokenizer ({'part-aware, ' if cfg.model.tokenizer.part_aware else ''}{cfg.model.tokenizer.num_codes} codes of "
                    f"{cfg.model.tokenizer.code_dim} dims, width {cfg.model.tokenizer.width}) on {cfg.data.name} ({fingerprint}), "
                    f"normalized with the {cfg.normalization.statistics} statistics.",
    )
    result, _, _ = tracked_fit(run, cfg, module, run_dir, build_callbacks(cfg), datamodule=datamodule, ckpt_path=ckpt_path, run_id=run_id)
    return result

"""Stage 1: train the motion tokenizer (`mmm train stage1 [key=value ...] [--resume last|PATH]`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import lightning as L
from omegaconf import DictConfig

from mmm.callbacks.checkpoints import CheckpointConfig
from mmm.callbacks.codebook import CodebookReset, CollapseConfig, CollapseMonitor
from mmm.callbacks.previews import CodebookUsagePlot, ReconstructionPreview
from mmm.config import ConfigError, compose, to_object
from mmm.data.datamodule import DataConfig, TokenizerDataModule
from mmm.data.normalization import NormalizationConfig
from mmm.fingerprint import dataset_fingerprint
from mmm.kinds import STAGE1, STAGE1_PARTS
from mmm.tokenizer.module import DecoderRefineConfig, TokenizerLossConfig, TokenizerModule
from mmm.tokenizer.search import CodeSearchConfig
from mmm.tracking import TrackingConfig
from mmm.training.common import TrackedRun, TrainResult, run_target, tracked_fit
from mmm.training.configs import ModelConfig, TrainerConfig
from mmm.training.optim import OptimConfig


@dataclass
class Stage1Callbacks:
    reset_every_n_steps: int = 20  # CodebookReset every N steps; 0 disables codebook reset
    collapse: CollapseConfig = field(default_factory=CollapseConfig)
    preview_clips: int = 3  # ReconstructionPreview: validation clips rendered at each validation (0: none)
    usage_plot: bool = True  # CodebookUsagePlot at each validation
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)

    def __post_init__(self):
        for name in ("reset_every_n_steps", "preview_clips"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"callbacks.{name}={value!r}: must be a whole number, 0 or more (0: off)")


@dataclass
class Stage1Config:
    seed: int = 0
    output_dir: str = STAGE1.output_dir
    data: DataConfig = field(default_factory=DataConfig)
    normalization: NormalizationConfig = field(default_factory=NormalizationConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    loss: TokenizerLossConfig = field(default_factory=TokenizerLossConfig)
    refine: DecoderRefineConfig = field(default_factory=DecoderRefineConfig)
    encode: CodeSearchConfig = field(default_factory=CodeSearchConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    logger: TrackingConfig = field(default_factory=TrackingConfig)
    callbacks: Stage1Callbacks = field(default_factory=Stage1Callbacks)


def load_stage1_config(overrides: list[str] = (), parts: bool = False) -> DictConfig:
    """conf/train_stage1.yaml, or with parts=True conf/train_stage1_parts.yaml (the part-aware tokenizer)."""
    return compose((STAGE1_PARTS if parts else STAGE1).config, list(overrides), schema=Stage1Config)


def build_callbacks(cfg: Stage1Config) -> list[L.Callback]:
    cb = cfg.callbacks
    callbacks: list[L.Callback] = [
        CodebookReset(cb.reset_every_n_steps),
        CollapseMonitor(**asdict(cb.collapse)),
    ]
    if cb.preview_clips > 0:
        callbacks.append(ReconstructionPreview(cb.preview_clips))
    if cb.usage_plot:
        callbacks.append(CodebookUsagePlot())
    return callbacks


def train_stage1(cfg_node: DictConfig, resume: str | None = None) -> TrainResult:
    """Train a tokenizer as configured; `resume` = "last" or a checkpoint path continues a run
    (a checkpoint outside this stage's run folders is only read: the run goes on in a new folder)."""
    cfg: Stage1Config = to_object(cfg_node)
    if cfg.refine.steps < 0:  # (trainer.max_steps >= 1 is TrainerConfig's own check)
        raise ConfigError(
            f"refine.steps={cfg.refine.steps}: the decoder refinement's steps after trainer.max_steps steps "
            "of the whole tokenizer must be 0 or more (0: no refinement)"
        )
    cfg.trainer.max_steps += cfg.refine.steps  # the fit: the whole tokenizer, then the decoder alone
    L.seed_everything(cfg.seed, workers=True)
    target = run_target(cfg, resume)
    datamodule = TokenizerDataModule(
        cfg.data,
        seed=cfg.seed,
        normalization=cfg.normalization,
        start_windows=cfg.refine.start_windows if cfg.refine.steps > 0 else 0.0,
    )
    datamodule.prepare_data()
    datamodule.setup("fit")
    module = TokenizerModule(
        cfg.data.feature_dim,
        cfg.model.tokenizer,
        cfg.optim,
        cfg.loss,
        datamodule.mean,
        datamodule.std,
        cfg.refine,
        cfg.encode,
    )
    fingerprint = dataset_fingerprint(cfg.data.root)
    tokenizer = cfg.model.tokenizer
    run = TrackedRun(
        STAGE1_PARTS if tokenizer.part_aware else STAGE1,
        cfg_node,
        exclude=("model.transformer",),
        model_cfg=cfg.model,
        tags={"data.name": cfg.data.name, "data.root": cfg.data.root, "data.fingerprint": fingerprint},
        dataset=(cfg.data.name, cfg.data.root, fingerprint),
        description=f"Tokenizer ({'part-aware, ' if tokenizer.part_aware else ''}"
        f"{tokenizer.num_codes} codes of "
        f"{tokenizer.code_dim} dims, width {tokenizer.width}) on {cfg.data.name} ({fingerprint}), "
        f"normalized with the {cfg.normalization.statistics} statistics.",
    )
    result, _, _ = tracked_fit(run, cfg, module, target, build_callbacks(cfg), datamodule=datamodule)
    return result

"""What each training command reads: `mmm train stage1|stage1-parts|stage2|stage2-parts|length|
evaluator` (conf/train_*.yaml), from the sections every trainer shares (model sizes, the trainer)
to each kind's callbacks and its whole config (Stage1Config, Stage2Config, ...), made of the
sections the other packages define in their own configs.py; and the contrastive evaluator's
network and loss settings (its network, mmm.evaluation.contrastive, needs torchmetrics to load).

Kept apart from the LightningModules and trainers so that a config is composed and checked without
loading Lightning or MLflow: a misspelt key or an out-of-range value is refused in about a second,
not after the several seconds those imports take."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig

from mmm.callbacks.configs import CheckpointConfig, CollapseConfig, check_weight_ema
from mmm.config import ConfigError, check_whole, compose
from mmm.data.configs import DataConfig
from mmm.data.normalization import NormalizationConfig
from mmm.generation.length import LengthModelConfig
from mmm.kinds import EVALUATOR, LENGTH, STAGE1, STAGE1_PARTS, STAGE2, STAGE2_PARTS
from mmm.optim import OptimConfig
from mmm.text.encoders import TextConfig
from mmm.tokenizer.configs import DecoderRefineConfig, TokenizerLossConfig
from mmm.tokenizer.network import TokenizerConfig
from mmm.tokenizer.search import CodeSearchConfig
from mmm.tracking import TrackingConfig
from mmm.transformer.configs import CorruptionConfig
from mmm.transformer.network import TransformerConfig


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
    precision: str = "32-true"  # Lightning's names, or auto: bf16-mixed where the device has bfloat16 kernels
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

    def __post_init__(self):
        # Lightning takes max_steps -1 as "no limit" and 0 as "train nothing", and divides by the
        # other two: none of that is a training run here.
        for name in ("max_steps", "val_check_interval", "log_every_n_steps"):
            example = ", e.g. trainer.max_steps=1000" if name == "max_steps" else ""
            check_whole(f"trainer.{name}", getattr(self, name), 1, f" (steps{example})")


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


def check_first_validation(steps: int, every: int) -> None:
    """Checkpoints are written at validations: refuse a fit of `steps` steps that ends before its
    first one (trainer.val_check_interval=`every`), which would finish with no model."""
    if every > steps:
        raise ConfigError(
            f"the fit's {steps} steps end before its first validation (trainer.val_check_interval={every}), "
            f"so no checkpoint would be written: set trainer.val_check_interval to at most {steps}"
        )


def _checked(cfg_node: DictConfig, extra_steps: int = 0) -> DictConfig:
    trainer = cfg_node.trainer
    check_first_validation(trainer.max_steps + extra_steps, trainer.val_check_interval)
    return cfg_node


def load_stage1_config(overrides: list[str] = (), parts: bool = False) -> DictConfig:
    """conf/train_stage1.yaml, or with parts=True conf/train_stage1_parts.yaml (the part-aware tokenizer)."""
    cfg = compose((STAGE1_PARTS if parts else STAGE1).config, list(overrides), schema=Stage1Config)
    return _checked(cfg, cfg.refine.steps)  # the fit: the whole tokenizer, then the decoder alone


@dataclass
class Stage2Callbacks:
    checkpoint: CheckpointConfig = field(
        default_factory=lambda: CheckpointConfig(monitor="val/loss", mode="min")
    )
    # GenerationPreview: validation captions generated and rendered at each validation (0: none)
    preview_captions: int = 3
    # AdherenceCurve: labelled validation captions generated and checked at each validation, logged
    # as val_adherence/* (0: none; only on a dataset with labels/, whole-body models)
    adherence_captions: int = 64
    # WeightEMA: validation, previews, the curve and the checkpoints use an exponential moving average
    # of the weights with this decay (0: none, the weights as trained)
    weight_ema: float = 0.0

    def __post_init__(self):
        check_weight_ema(self.weight_ema)


@dataclass
class Stage2Config:
    seed: int = 0
    output_dir: str = STAGE2.output_dir
    stage1: str | None = None  # checkpoint path, MLflow run id, models:/NAME@ALIAS; None: the newest
    stage1_output_dir: str = STAGE1.output_dir
    stage1_experiment: str = (
        STAGE1.experiment
    )  # where the newest stage-1 run is looked for (mmm-stage1-parts: part-aware)
    part_aware: bool = (
        False  # the part-aware transformer (upper body given lower body); needs a part-aware stage-1 model
    )
    token_cache_dir: str = "outputs/cache/tokens"
    # The codes stage 2 learns from: `tokenizer`, the stage-1 model's own `encode` setting (the code
    # search for this package's tokenizers), or `nearest`, the nearest code (seconds instead of
    # minutes; what the release trains on).
    token_encoding: str = "tokenizer"
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    corruption: CorruptionConfig = field(default_factory=CorruptionConfig)
    text: TextConfig = field(default_factory=TextConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    logger: TrackingConfig = field(default_factory=TrackingConfig)
    callbacks: Stage2Callbacks = field(default_factory=Stage2Callbacks)

    def __post_init__(self):
        if self.token_encoding not in TOKEN_ENCODINGS:
            raise ValueError(
                f"token_encoding={self.token_encoding!r}: must be one of {', '.join(TOKEN_ENCODINGS)} "
                "(tokenizer: the stage-1 model's own encode setting; nearest: the nearest code)"
            )


TOKEN_ENCODINGS = ("tokenizer", "nearest")


def load_stage2_config(overrides: list[str] = (), parts: bool = False) -> DictConfig:
    """conf/train_stage2.yaml, or with parts=True conf/train_stage2_parts.yaml (the part-aware
    transformer)."""
    return _checked(compose((STAGE2_PARTS if parts else STAGE2).config, list(overrides), schema=Stage2Config))


@dataclass
class ValLossCallbacks:
    """The length estimator's and the evaluator's callbacks: best.ckpt by the validation loss."""

    checkpoint: CheckpointConfig = field(
        default_factory=lambda: CheckpointConfig(monitor="val/loss", mode="min")
    )


@dataclass
class LengthConfig:
    seed: int = 0
    output_dir: str = LENGTH.output_dir
    stage1: str | None = None  # checkpoint path, MLflow run id, models:/NAME@ALIAS; None: the newest
    stage1_output_dir: str = STAGE1.output_dir
    token_cache_dir: str = "outputs/cache/tokens"
    data: DataConfig = field(default_factory=DataConfig)
    text: TextConfig = field(default_factory=TextConfig)
    model: LengthModelConfig = field(default_factory=LengthModelConfig)
    optim: OptimConfig = field(
        default_factory=lambda: OptimConfig(
            lr=1e-3, betas=[0.9, 0.999], weight_decay=1e-2, warmup_steps=20, milestones=[1_000_000]
        )
    )
    label_smoothing: float = 0.0
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    logger: TrackingConfig = field(default_factory=lambda: TrackingConfig(experiment=LENGTH.experiment))
    callbacks: ValLossCallbacks = field(default_factory=ValLossCallbacks)


def load_length_config(overrides: list[str] = ()) -> DictConfig:
    return _checked(compose(LENGTH.config, list(overrides), schema=LengthConfig))


@dataclass
class ContrastiveModelConfig:
    embed_dim: int = 512  # E: the shared embedding size
    hidden_dim: int = 256  # H: conv channels and GRU hidden size per direction
    text_hidden_dim: int = 512  # the text head's hidden layer
    dropout: float = 0.1
    normalize: bool = True  # L2-normalize the embeddings embed_* return
    init_temperature: float = 0.07
    max_logit_scale: float = 100.0  # 1 / the lowest temperature

    def __post_init__(self):
        if min(self.embed_dim, self.hidden_dim, self.text_hidden_dim) < 1:
            raise ValueError(
                "contrastive evaluator: embed_dim, hidden_dim and text_hidden_dim must be positive, got "
                f"{self}"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"contrastive evaluator: dropout must be in [0, 1), got {self.dropout}")
        if self.init_temperature <= 0 or 1.0 / self.init_temperature > self.max_logit_scale:
            raise ValueError(
                "contrastive evaluator: init_temperature must be positive and at least 1 / max_logit_scale, "
                f"got {self.init_temperature}"
            )


@dataclass
class ContrastiveLossConfig:
    # Pairs (i, j) whose frozen sentence embeddings have cosine >= this are not negatives of each
    # other (the same caption twice in a batch, or a paraphrase); null: every other pair is one.
    false_negative_threshold: float | None = 0.95
    # Hard negatives: each caption's counterfactuals of these kinds ("count", "speed";
    # mmm.text.counterfactuals) compete with it for its motion; [] trains on in-batch
    # negatives only. conf/train_evaluator.yaml asks for [count]: the better judge for best of N.
    counterfactuals: list[str] = field(default_factory=list)
    # Under DDP, every rank's pairs are negatives of every other's: the loss and its gradient are
    # those of one process on the whole batch (mmm.evaluation.contrastive_module.global_batch);
    # false: each rank contrasts only its own pairs, as with a per-rank batch.
    global_negatives: bool = True


@dataclass
class RetrievalConfig:
    """Validation and test retrieval: pairs in batches of batch_size (32 by the protocol)."""

    batch_size: int = 32
    seed: int = 0  # the test split's order and its caption/crop draws


@dataclass
class RegistryConfig:
    register: bool = True
    name: str = EVALUATOR.registered


@dataclass
class EvaluatorTrainConfig:
    seed: int = 0
    output_dir: str = EVALUATOR.output_dir
    data: DataConfig = field(default_factory=lambda: DataConfig(batch_size=128))
    text: TextConfig = field(default_factory=TextConfig)
    model: ContrastiveModelConfig = field(default_factory=ContrastiveModelConfig)
    loss: ContrastiveLossConfig = field(default_factory=ContrastiveLossConfig)
    optim: OptimConfig = field(
        default_factory=lambda: OptimConfig(
            lr=1e-3, betas=[0.9, 0.999], weight_decay=1e-2, warmup_steps=50, milestones=[1_000_000]
        )
    )
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    logger: TrackingConfig = field(default_factory=lambda: TrackingConfig(experiment=EVALUATOR.experiment))
    callbacks: ValLossCallbacks = field(default_factory=ValLossCallbacks)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    registry: RegistryConfig = field(default_factory=RegistryConfig)


def load_evaluator_config(overrides: list[str] = ()) -> DictConfig:
    return _checked(compose(EVALUATOR.config, list(overrides), schema=EvaluatorTrainConfig))

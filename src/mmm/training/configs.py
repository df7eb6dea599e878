"""The config sections every trainer shares: the model sizes of both stages and the trainer
(conf/model/*.yaml, conf/trainer/*.yaml). Each stage's own config (Stage1Config, ...) lives with
its trainer; the callback configs live with their callbacks (mmm.callbacks)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from mmm.config import check_whole
from mmm.tokenizer.network import TokenizerConfig
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

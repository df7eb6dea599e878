"""Stage 2's training corruption (conf/train_stage2.yaml `corruption:`): masking schedule, random
codes, the loss's positions, text dropout. Apart from the LightningModule (module.py) so that a
config is checked without loading Lightning."""

from __future__ import annotations

from dataclasses import dataclass

from mmm.transformer.schedules import TRAINING_SCHEDULES, check_schedule


@dataclass
class CorruptionConfig:
    mask_schedule: str = (
        "uniform"  # a name of transformer/schedules.py TRAINING_SCHEDULES (uniform: as released)
    )
    pkeep: float = 0.5  # real tokens replaced by random codes with probability 1 - pkeep
    loss_on: str = "all"  # all real positions (released) | masked
    cond_drop: float = 0.0  # probability of dropping the text (0.1 enables classifier-free guidance)
    lower_mask: float = (
        1.0  # part-aware model: a share ~ U(0, lower_mask) of the lower-body condition codes is masked
    )

    def __post_init__(self):
        check_schedule(self.mask_schedule, TRAINING_SCHEDULES, "corruption.mask_schedule")
        if self.loss_on not in ("all", "masked"):
            raise ValueError(f"corruption.loss_on must be all or masked, got {self.loss_on!r}")
        if not 0.0 <= self.cond_drop < 1.0:
            raise ValueError(
                "corruption.cond_drop is the probability of dropping the text, in [0, 1) (1 would never "
                f"show the model a caption; 0.1 enables classifier-free guidance), got {self.cond_drop}"
            )
        if not 0.0 <= self.pkeep <= 1.0:
            raise ValueError(
                f"corruption.pkeep is the share of real tokens kept, in [0, 1], got {self.pkeep}"
            )
        if not 0.0 <= self.lower_mask <= 1.0:
            raise ValueError(f"corruption.lower_mask is a share in [0, 1], got {self.lower_mask}")

"""The optimizer and learning-rate schedule of every model this package trains.

AdamW with a linear warm-up over `warmup_steps` optimizer steps, then the rate times `gamma` at
each of `milestones` and where the run's last `final_share` of steps begins; the scheduler steps
with the optimizer and Lightning's LearningRateMonitor charts it as `train/lr`. Each
LightningModule's `configure_optimizers` is one call to `build_optimizer`. Only torch and
dataclasses here: the model packages import this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import torch


@dataclass
class OptimConfig:
    lr: float = 2e-4
    betas: list[float] = field(default_factory=lambda: [0.9, 0.99])
    weight_decay: float = 0.0
    warmup_steps: int = 1000
    milestones: list[int] = field(default_factory=lambda: [200_000])  # lr *= gamma at each
    gamma: float = 0.05
    # lr *= gamma once more for the last share of the run's optimizer steps (one more milestone,
    # placed from the trainer's step count, so it moves with trainer.max_steps); 0: none
    final_share: float = 0.0

    def __post_init__(self):
        if not 0.0 <= self.final_share < 1.0:
            raise ValueError(
                f"optim.final_share={self.final_share!r}: the share of the run's last steps at the "
                "rate x gamma must be in [0, 1), e.g. optim.final_share=0.25 (0: none)"
            )

    def milestones_for(self, total_steps: int | None) -> list[int]:
        """`milestones`, with the start of the run's last `final_share` of `total_steps` (at least
        one step) when it is set."""
        if not self.final_share:
            return list(self.milestones)
        if total_steps is None or total_steps <= 0:
            raise ValueError(
                f"optim.final_share={self.final_share} needs a run of known length, got {total_steps} "
                "optimizer steps; set trainer.max_steps, or optim.final_share=0"
            )
        return sorted([*self.milestones, final_drop_step(total_steps, self.final_share)])


def final_drop_step(total_steps: int, final_share: float) -> int:
    """The optimizer step where a run of `total_steps` begins its last `final_share` (at least one step)."""
    # rounded first: 0.3 x 10 is 3.0000000000000004 in floating point, which is 3 steps
    return int(total_steps) - math.ceil(round(total_steps * final_share, 6))


def warmup_step_schedule(warmup_steps: int, milestones: list[int], gamma: float):
    """lr multiplier at optimizer step s: linear warm-up, then x gamma at each milestone."""

    def factor(step: int) -> float:
        warm = min(1.0, (step + 1) / warmup_steps) if warmup_steps > 0 else 1.0
        return warm * gamma ** sum(step >= m for m in milestones)

    return factor


def cosine_tail(schedule, start: int, steps: int, scale: float):
    """`schedule` (lr multiplier at step s) until `start`, then `scale` decaying to 0 along a
    half cosine over `steps` steps."""

    def factor(step: int) -> float:
        if step < start:
            return schedule(step)
        done = min(step - start, steps) / steps
        return scale * 0.5 * (1.0 + math.cos(math.pi * done))

    return factor


def build_optimizer(
    parameters: Iterable[torch.nn.Parameter],
    cfg: OptimConfig,
    *,
    foreach: bool | None = None,
    decay_matrices_only: bool = False,
    tail: tuple[int, int, float] | None = None,
    total_steps: int | None = None,
) -> dict:
    """AdamW over `parameters` with the warm-up/step schedule of `cfg`, as Lightning's
    `configure_optimizers` returns it: {"optimizer", "lr_scheduler": {scheduler, per step, `train/lr`}}.

    foreach: AdamW's multi-tensor implementation (None: torch's default for the device).
    decay_matrices_only: weight decay on the trainable weight matrices only (dim >= 2), none on
    biases, norms and scalars such as a logit scale; otherwise on every parameter.
    tail: (start, steps, scale): from step `start` on, the rate is cfg.lr x scale decaying to 0
    along a half cosine over `steps` (`cosine_tail`; the tokenizer's decoder refinement).
    total_steps: the run's optimizer steps (`trainer.max_steps`), which place `cfg.final_share`;
    needed only when that is set.
    """
    if decay_matrices_only:
        trainable = [p for p in parameters if p.requires_grad]
        parameters = [
            {"params": [p for p in trainable if p.dim() >= 2], "weight_decay": cfg.weight_decay},
            {"params": [p for p in trainable if p.dim() < 2], "weight_decay": 0.0},
        ]
    optimizer = torch.optim.AdamW(
        parameters, lr=cfg.lr, betas=tuple(cfg.betas), weight_decay=cfg.weight_decay, foreach=foreach
    )
    factor = warmup_step_schedule(cfg.warmup_steps, cfg.milestones_for(total_steps), cfg.gamma)
    if tail is not None:
        factor = cosine_tail(factor, *tail)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
    return {
        "optimizer": optimizer,
        "lr_scheduler": {"scheduler": schedule, "interval": "step", "name": "train/lr"},
    }

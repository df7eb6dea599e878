"""The masking schedules, training and decoding, in one place.

Training (`corruption.mask_schedule`): u ~ U(0, 1) per sequence -> the share of its codes masked.
Decoding (`sampling.schedule`, `--schedule`): progress t = (pass + 1) / passes in [0, 1] -> the
share of the free codes still masked after that pass (1 at t = 0, 0 at t = 1).

To add a schedule, add one function to the dictionary it belongs to: the config checks, the CLI's
choices and the ablation grid take their names from these dictionaries.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:  # the schedules only call tensor methods: importing them costs no torch (the CLI's checks)
    import torch

TRAINING_SCHEDULES: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "uniform": lambda u: 0.5 + 0.5 * u,  # ratio ~ U(0.5, 1), as the released code trains
    "cosine": lambda u: (math.pi / 2 * u).cos(),  # MaskGIT's: cos(pi/2 u)
}

DECODING_SCHEDULES: dict[str, Callable[[float], float]] = {
    "cosine": lambda t: math.cos(math.pi / 2 * t),
    "linear": lambda t: 1.0 - t,
    "square": lambda t: 1.0 - t * t,  # convex; the paper's "square root" row
}


def check_schedule(name: str, schedules: dict, key: str) -> str:
    """`name` when it is one of `schedules`, else a ValueError naming the config key and the choices."""
    if name not in schedules:
        raise ValueError(f"{key} must be one of {', '.join(schedules)}, got {name!r}")
    return name

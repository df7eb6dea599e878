"""The callbacks' settings (conf/callbacks/*.yaml): which checkpoint is best, when a codebook
counts as collapsed, and the decay of the weights' moving average. Apart from the callbacks so
that a config is checked without loading Lightning."""

from __future__ import annotations

from dataclasses import dataclass

from mmm.config import ConfigError


@dataclass
class CheckpointConfig:
    monitor: str = "val/mpjpe_root_aligned_mm"
    mode: str = "min"


@dataclass
class CollapseConfig:
    """CollapseMonitor's settings (`callbacks.collapse` of conf/callbacks/stage1.yaml)."""

    action: str = "warn"  # warn | stop | fail
    warmup_steps: int = 200
    window_steps: int = 50
    min_active_fraction: float = 0.02
    perplexity_drop: float = 0.2
    smoothing: float = 0.9
    patience: int = 3


def check_weight_ema(decay, name: str = "callbacks.weight_ema") -> bool:
    """Whether the weights are averaged (a decay in (0, 1)); a value outside [0, 1) is refused."""
    if isinstance(decay, bool) or not isinstance(decay, (int, float)) or not 0.0 <= decay < 1.0:
        raise ConfigError(
            f"{name}={decay!r}: the decay of the weights' moving average must be in [0, 1), "
            f"e.g. {name}=0.99 (about the last 100 steps), or 0 for none"
        )
    return decay > 0

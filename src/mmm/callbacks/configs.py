"""The callbacks' settings (conf/callbacks/*.yaml): which checkpoint is best, and when a codebook
counts as collapsed. Apart from the callbacks so that a config is checked without loading
Lightning."""

from __future__ import annotations

from dataclasses import dataclass


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

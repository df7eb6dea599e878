"""The data section of every config (conf/data/*.yaml): which dataset, its filters and batches.

Kept apart from the LightningDataModules (datamodule.py) so that a config is composed and checked
without loading Lightning: a misspelt key or an out-of-range value is refused in about a second."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from mmm.config import ConfigError, check_whole
from mmm.data.humanml3d import LoadReport, load_clips, load_items
from mmm.data.synthetic.generate import COMPOSITE_FRACTION
from mmm.motion.skeleton import SKELETONS, Skeleton


@dataclass
class SynthConfig:
    """Generate the synthetic dataset into `root` when it is missing."""

    num_clips: int = 1500
    seed: int = 0
    train_paraphrases: int = 3  # whole-clip captions per training clip (3 = every clip's own)
    extra_train_clips: int = 0  # more clips, all in the training split (val and test unchanged)
    extra_composite_fraction: float = COMPOSITE_FRACTION  # share of two-action clips among those


@dataclass
class OversampleConfig:
    """Stage 2's training items with a caption that matches `pattern` (a Python regular expression,
    searched case-insensitively) are drawn `factor` times per epoch; an empty pattern turns it off.
    The validation and test splits, stage 1 and the evaluator read the data as it is."""

    pattern: str = ""
    factor: int = 2


@dataclass
class DataConfig:
    name: str = "synthetic"
    root: str = "data/synthetic"
    skeleton: str = "t2m"  # t2m: 22 joints, 263 dims; kit: 21 joints, 251 dims
    fps: float = 20.0
    min_length: int = 40  # motions and caption spans shorter than this are left out
    length_limit: int = 200  # ... and those this long or longer
    max_length: int = 196  # stage 2 crops to at most this many frames
    unit_length: int = 4  # the tokenizer's temporal downsampling
    window: int = 64  # stage 1 training windows
    batch_size: int = 64
    num_workers: int = 0
    on_invalid: str = "error"  # error | skip (skipped clips are counted and logged)
    synthesize: SynthConfig | None = field(default=None)
    oversample: OversampleConfig = field(default_factory=OversampleConfig)

    def __post_init__(self):
        bounds = (
            ("batch_size", 1),
            ("unit_length", 1),
            ("window", self.unit_length),
            ("num_workers", 0),
            ("min_length", 1),
            ("max_length", self.unit_length),
        )
        for name, least in bounds:
            check_whole(f"data.{name}", getattr(self, name), least)
        check_whole(
            "data.length_limit",
            self.length_limit,
            self.min_length + 1,
            f" (more than data.min_length={self.min_length})",
        )
        if not (isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0):
            raise ConfigError(
                f"data.fps={self.fps!r}: must be a number of frames per second above 0 (20 for HumanML3D)"
            )
        if self.window % self.unit_length:
            raise ConfigError(
                f"data.window={self.window} is not a multiple of data.unit_length={self.unit_length} (the "
                "tokenizer's downsampling): use e.g. "
                f"data.window={self.window // self.unit_length * self.unit_length}"
            )

    @property
    def skeleton_def(self) -> Skeleton:
        if self.skeleton not in SKELETONS:
            raise ValueError(f"data.skeleton={self.skeleton!r} is unknown; use one of {sorted(SKELETONS)}")
        return SKELETONS[self.skeleton]

    @property
    def feature_dim(self) -> int:
        return self.skeleton_def.feature_dim

    def items(self, split: str, root: str | Path | None = None) -> tuple[list, LoadReport]:
        """(caption items, report) of `split` under this config's filters (lengths, invalid clips)."""
        return load_items(
            root or self.root,
            split,
            feature_dim=self.feature_dim,
            fps=self.fps,
            min_length=self.min_length,
            length_limit=self.length_limit,
            on_invalid=self.on_invalid,
        )

    def clips(self, split: str, root: str | Path | None = None) -> tuple[list, LoadReport]:
        """(whole motions, report) of `split` under this config's filters."""
        return load_clips(
            root or self.root,
            split,
            feature_dim=self.feature_dim,
            min_length=self.min_length,
            on_invalid=self.on_invalid,
        )

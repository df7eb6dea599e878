"""The statistics the tokenizer normalizes motion with (kept in its checkpoint, used downstream).

`dataset`: the dataset's Mean.npy/Std.npy. `evaluator_style`: the same, with the Std of the root
(yaw velocity, x/z velocity, height: dims 0-3) and foot-contact (last 4) groups divided by
`feat_bias` (25): the statistics the released MMM trains with (the T2M evaluator's meta/std.npy
is HumanML3D's Std divided by 24.9-25.25 on exactly those dims, within 0.4% elsewhere). In that
space those 8 dims are ~25x larger, so the reconstruction loss weighs the root path and the
contacts ~25x more. `files`: mean.npy/std.npy (or Mean.npy/Std.npy) from a folder, e.g. the T2M
evaluator's meta folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mmm.data.humanml3d import DataError, load_stats
from mmm.motion.features import FeatureLayout
from mmm.motion.skeleton import skeleton_for

STATISTICS = ("dataset", "evaluator_style", "files")


@dataclass
class NormalizationConfig:
    statistics: str = "dataset"  # dataset | evaluator_style | files
    feat_bias: float = 25.0  # evaluator_style: root and foot-contact Std divided by this
    dir: str | None = None  # files: the folder holding mean.npy and std.npy

    def __post_init__(self):
        if self.statistics not in STATISTICS:
            raise ValueError(
                f"normalization.statistics must be one of {', '.join(STATISTICS)}, got {self.statistics!r}"
            )
        if not (np.isfinite(self.feat_bias) and self.feat_bias > 0):
            raise ValueError(f"normalization.feat_bias must be a finite number above 0, got {self.feat_bias}")
        if self.statistics == "files" and not self.dir:
            raise ValueError(
                "normalization.statistics=files needs normalization.dir=FOLDER (with mean.npy and std.npy)"
            )


def evaluator_style_std(std: np.ndarray, num_joints: int, feat_bias: float = 25.0) -> np.ndarray:
    """Std (D,) with the root groups (dims 0-3) and the foot contacts (last 4) divided by feat_bias."""
    layout = FeatureLayout(num_joints)
    out = np.array(std, dtype=np.float32, copy=True)
    for group in (layout.root_yaw, layout.root_velocity, layout.root_height, layout.contacts):
        out[group] /= feat_bias
    return out


def read_stats_folder(folder: str | Path, feature_dim: int) -> tuple[np.ndarray, np.ndarray]:
    """mean.npy/std.npy (or Mean.npy/Std.npy) of a folder, checked: (D,) finite, std > 0."""
    folder = Path(folder)
    out = []
    for names in (("mean.npy", "Mean.npy"), ("std.npy", "Std.npy")):
        path = next((folder / n for n in names if (folder / n).is_file()), None)
        if path is None:
            raise DataError(
                folder,
                f"neither {names[0]} nor {names[1]} is there",
                "give the folder holding the normalization statistics",
            )
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as e:
            raise DataError(
                path, f"not a readable .npy array ({type(e).__name__})", "write it again with numpy.save"
            ) from None
        if (
            arr.shape != (feature_dim,)
            or not np.issubdtype(arr.dtype, np.floating)
            or not np.isfinite(arr).all()
        ):
            raise DataError(
                path,
                f"expected {feature_dim} finite floats, got {arr.dtype} {arr.shape}",
                "use statistics of this dataset's features",
            )
        out.append(arr.astype(np.float32))
    if (out[1] <= 0).any():
        raise DataError(folder, "std has zero or negative entries", "recompute the statistics")
    return out[0], out[1]


def tokenizer_statistics(
    cfg: NormalizationConfig, root: str | Path, feature_dim: int
) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) (D,) the tokenizer normalizes with, as configured."""
    if cfg.statistics == "files":
        return read_stats_folder(cfg.dir, feature_dim)
    mean, std = load_stats(root, feature_dim)
    if cfg.statistics == "evaluator_style":
        std = evaluator_style_std(std, skeleton_for(feature_dim).num_joints, cfg.feat_bias)
    return mean, std

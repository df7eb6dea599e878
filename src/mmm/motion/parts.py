"""The lower/upper body split of the 263-d HumanML3D features (method.md, upper-body editing).

Lower body = pelvis, hips, knees, ankles and feet: the 4 root features, those joints' positions,
rotations and velocities, and the 4 foot contacts (107 dims). Upper body = the other 13 joints'
positions, rotations and velocities (156 dims). The root belongs to the lower body because it is
the legs that move it; the contacts because they are the feet's.

Only the 22-joint skeleton is split: KIT-ML's 21 joints have no agreed split.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from mmm.motion.features import FeatureLayout
from mmm.motion.skeleton import T2M_SKELETON

LOWER_JOINT_NAMES = (
    "pelvis",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_foot",
    "right_foot",
)
LOWER_JOINTS = tuple(sorted(T2M_SKELETON.joint_names.index(name) for name in LOWER_JOINT_NAMES))
UPPER_JOINTS = tuple(j for j in range(T2M_SKELETON.num_joints) if j not in LOWER_JOINTS)

_DIM = FeatureLayout(T2M_SKELETON.num_joints).dim


def _joint_dims(layout: FeatureLayout, joint: int) -> list[int]:
    """Feature dims of one joint: its position and rotation (joints 1.. only: the root's are
    implicit) and its velocity."""
    dims = []
    if joint > 0:
        dims += range(layout.positions.start + 3 * (joint - 1), layout.positions.start + 3 * joint)
        dims += range(layout.rotations.start + 6 * (joint - 1), layout.rotations.start + 6 * joint)
    dims += range(layout.velocities.start + 3 * joint, layout.velocities.start + 3 * (joint + 1))
    return dims


@functools.lru_cache(maxsize=None)
def part_indices(num_joints: int = 22) -> tuple[np.ndarray, np.ndarray]:
    """Sorted feature indices (107,) of the lower body and (156,) of the upper body.

    The arrays are cached and read-only; copy them to modify.
    """
    if num_joints != T2M_SKELETON.num_joints:
        raise ValueError(
            "the lower/upper body split is defined for the 22-joint HumanML3D skeleton only, got "
            f"num_joints={num_joints}"
            + (" (KIT-ML): train a plain tokenizer for KIT-ML" if num_joints == 21 else "")
        )
    layout = FeatureLayout(num_joints)
    lower = [
        *range(layout.root_yaw.start, layout.root_height.stop),
        *range(layout.contacts.start, layout.contacts.stop),
    ]
    for joint in LOWER_JOINTS:
        lower += _joint_dims(layout, joint)
    upper = [d for joint in UPPER_JOINTS for d in _joint_dims(layout, joint)]
    lower_idx, upper_idx = np.array(sorted(lower), dtype=np.int64), np.array(sorted(upper), dtype=np.int64)
    for idx in (lower_idx, upper_idx):
        idx.setflags(write=False)
    return lower_idx, upper_idx


@functools.lru_cache(maxsize=None)
def _merge_order() -> np.ndarray:
    """Permutation that puts the concatenation [lower, upper] back in feature order."""
    lower_idx, upper_idx = part_indices()
    order = np.argsort(np.concatenate((lower_idx, upper_idx)))
    order.setflags(write=False)
    return order


def _check_width(name: str, x, expected: int, hint: str = "") -> None:
    if x.shape[-1] != expected:
        raise ValueError(
            f"{name} must have {expected} values in the last dim, got shape {tuple(x.shape)}{hint}"
        )


def _take(x, idx: np.ndarray):
    """x[..., idx] for a numpy array or a torch tensor (indices moved to its device)."""
    if isinstance(x, torch.Tensor):
        return x[..., torch.tensor(idx, device=x.device)]
    return np.asarray(x)[..., idx]


def split_parts(x):
    """(lower (..., 107), upper (..., 156)) of features x (..., 263), numpy or torch."""
    kit = FeatureLayout(21).dim
    hint = (
        f" ({kit} is KIT-ML's 21-joint layout: the split supports only the 22-joint HumanML3D skeleton)"
        if x.shape[-1] == kit
        else ""
    )
    _check_width("features", x, _DIM, hint)
    lower_idx, upper_idx = part_indices()
    return _take(x, lower_idx), _take(x, upper_idx)


def merge_parts(lower, upper):
    """Features (..., 263) of lower (..., 107) and upper (..., 156); the inverse of `split_parts`.

    Built by concatenation and a gather (no in-place writes), so gradients flow to both parts.
    """
    lower_idx, upper_idx = part_indices()
    _check_width("lower", lower, len(lower_idx))
    _check_width("upper", upper, len(upper_idx))
    if lower.shape[:-1] != upper.shape[:-1]:
        raise ValueError(
            f"lower and upper must have the same leading shape, got {tuple(lower.shape)} and "
            f"{tuple(upper.shape)}"
        )
    if isinstance(lower, torch.Tensor):
        return _take(torch.cat((lower, torch.as_tensor(upper, device=lower.device)), dim=-1), _merge_order())
    return _take(np.concatenate((lower, upper), axis=-1), _merge_order())


__all__ = ["LOWER_JOINTS", "LOWER_JOINT_NAMES", "UPPER_JOINTS", "merge_parts", "part_indices", "split_parts"]

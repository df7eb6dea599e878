"""Joint positions <-> the HumanML3D rotation-invariant features (263-d for 22 joints).

Layout of one frame for K joints (motion-format.md):
    [0]                       root yaw velocity (half the per-frame heading change)
    [1:3]                     root linear velocity (x, z) in the heading frame
    [3]                       root height
    [4 : 4+3(K-1)]            joints 1..K-1 relative to the root in x/z, in the heading frame
    [.. : ..+6(K-1)]          joints 1..K-1 rotations, continuous 6-D
    [.. : ..+3K]              joint velocities in the heading frame
    [-4:]                     foot contacts L_ankle, L_foot, R_ankle, R_foot

Every public function takes and returns either numpy arrays or torch tensors (the type it is
given); numpy inputs are computed in float64 and returned in their own dtype.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

from mmm.motion.quaternion import qbetween, qinv, qmul, qrot, quat_to_cont6d
from mmm.motion.skeleton import T2M_SKELETON, Skeleton, forward_kinematics, inverse_kinematics, skeleton_for


@dataclass(frozen=True)
class FeatureLayout:
    """Slices of the feature vector for a skeleton of `num_joints` joints."""

    num_joints: int

    @property
    def dim(self) -> int:
        return 4 + (self.num_joints - 1) * 9 + self.num_joints * 3 + 4

    @property
    def root_yaw(self) -> slice:
        return slice(0, 1)

    @property
    def root_velocity(self) -> slice:
        return slice(1, 3)

    @property
    def root_height(self) -> slice:
        return slice(3, 4)

    @property
    def positions(self) -> slice:
        return slice(4, 4 + (self.num_joints - 1) * 3)

    @property
    def rotations(self) -> slice:
        start = self.positions.stop
        return slice(start, start + (self.num_joints - 1) * 6)

    @property
    def velocities(self) -> slice:
        start = self.rotations.stop
        return slice(start, start + self.num_joints * 3)

    @property
    def contacts(self) -> slice:
        start = self.velocities.stop
        return slice(start, start + 4)

    def groups(self) -> list[slice]:
        """The 7 groups inside which the reference replaces Std by the group mean."""
        return [
            self.root_yaw,
            self.root_velocity,
            self.root_height,
            self.positions,
            self.rotations,
            self.velocities,
            self.contacts,
        ]


def _array_api(fn):
    """Let a torch implementation take numpy arrays: float64 inside, the caller's dtype back."""

    @functools.wraps(fn)
    def wrapper(x, *args, **kwargs):
        if isinstance(x, torch.Tensor):
            return fn(x, *args, **kwargs)
        arr = np.asarray(x)
        out = fn(torch.from_numpy(arr.astype(np.float64)), *args, **kwargs)
        dtype = arr.dtype if np.issubdtype(arr.dtype, np.floating) else np.float32
        return out.numpy().astype(dtype)

    return wrapper


def _retarget(positions: torch.Tensor, skeleton: Skeleton) -> torch.Tensor:
    """Scale (T, J, 3) to the target skeleton's leg length and impose its bone lengths."""
    knee, ankle = skeleton.leg_joints
    src_lengths = skeleton.bone_lengths_of(positions[0])
    tgt_lengths = torch.tensor(skeleton.bone_lengths, dtype=positions.dtype)
    scale = (tgt_lengths[knee] + tgt_lengths[ankle]) / (src_lengths[knee] + src_lengths[ankle])
    quats = inverse_kinematics(positions, skeleton, smooth_forward=False)
    return forward_kinematics(
        quats, positions[:, 0] * scale, skeleton, skeleton.offsets(dtype=positions.dtype)
    )


@_array_api
def joints_to_features(
    joints,
    skeleton: Skeleton | None = None,
    *,
    retarget: bool = True,
    fix_yaw_flip: bool = True,
):
    """Features (T-1, D) of a motion given as joint positions (T, J, 3), D = 263 for 22 joints.

    Steps as in the reference pipeline: retarget to the target skeleton (when it has bone
    lengths), put the lowest point on the floor, move frame 0's root to x = z = 0, face +Z at
    frame 0, detect foot contacts, per-frame heading from the smoothed facing direction,
    rotations by inverse kinematics, then root and joint velocities.

    fix_yaw_flip: the reference takes arcsin of the relative heading quaternion without putting
    it in the w >= 0 hemisphere, so the yaw velocity flips sign on the frame where the heading
    crosses 180 degrees and the recovered path bends. True (default) fixes it; False
    reproduces the reference exactly.
    """
    if joints.ndim != 3 or joints.shape[-1] != 3:
        raise ValueError(f"joints must have shape (T, J, 3), got {tuple(joints.shape)}")
    skeleton = skeleton or skeleton_for(joints.shape[1])
    if joints.shape[1] != skeleton.num_joints:
        raise ValueError(
            f"skeleton {skeleton.name!r} has {skeleton.num_joints} joints, motion has {joints.shape[1]}"
        )
    if joints.shape[0] < 2:
        raise ValueError(f"a motion needs at least 2 frames to have velocities, got {joints.shape[0]}")
    positions = joints.clone()
    if retarget and skeleton.bone_lengths is not None:
        positions = _retarget(positions, skeleton)

    positions[..., 1] -= positions[..., 1].min()
    positions = positions - positions[0, 0] * positions.new_tensor([1.0, 0.0, 1.0])

    # Face +Z at frame 0 (here with the hips the right way round, as the reference does).
    r_hip, l_hip, r_sh, l_sh = skeleton.face_joints
    across = (positions[0, r_hip] - positions[0, l_hip]) + (positions[0, r_sh] - positions[0, l_sh])
    across = across / across.norm()
    forward = torch.linalg.cross(across.new_tensor([0.0, 1.0, 0.0]), across, dim=-1)
    forward = forward / forward.norm()
    init_quat = qbetween(forward, forward.new_tensor([0.0, 0.0, 1.0]))
    positions = qrot(init_quat, positions)
    global_positions = positions

    def contacts(foot: tuple[int, int]) -> torch.Tensor:
        disp = ((positions[1:, list(foot)] - positions[:-1, list(foot)]) ** 2).sum(-1)
        return (disp < skeleton.contact_threshold).to(positions.dtype)

    feet_l, feet_r = contacts(skeleton.left_foot), contacts(skeleton.right_foot)

    quats = inverse_kinematics(positions, skeleton, smooth_forward=True)
    cont6d = quat_to_cont6d(quats)
    r_rot = quats[:, 0]  # (T, 4): turns the smoothed heading to +Z

    root_velocity = qrot(r_rot[1:], positions[1:, 0] - positions[:-1, 0])
    r_velocity = qmul(r_rot[1:], qinv(r_rot[:-1]))
    if fix_yaw_flip:
        r_velocity = torch.where(r_velocity[:, :1] < 0, -r_velocity, r_velocity)

    root_xz = positions[:, 0:1] * positions.new_tensor([1.0, 0.0, 1.0])
    local = qrot(r_rot[:, None], positions - root_xz)

    T = positions.shape[0]
    yaw_velocity = torch.asin(r_velocity[:, 2:3].clamp(-1.0, 1.0))
    root_data = torch.cat((yaw_velocity, root_velocity[:, [0, 2]], local[:-1, 0, 1:2]), dim=-1)
    ric = local[:-1, 1:].reshape(T - 1, -1)
    rot = cont6d[:-1, 1:].reshape(T - 1, -1)
    velocity = qrot(r_rot[:-1, None], global_positions[1:] - global_positions[:-1]).reshape(T - 1, -1)
    return torch.cat((root_data, ric, rot, velocity, feet_l, feet_r), dim=-1)


def recover_root_rot_pos(features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Heading quaternions (..., T, 4) and root positions (..., T, 3) from features (..., T, D)."""
    yaw_velocity = features[..., 0]
    angle = torch.zeros_like(yaw_velocity)
    angle[..., 1:] = yaw_velocity[..., :-1]
    angle = torch.cumsum(angle, dim=-1)
    rot_quat = torch.zeros(features.shape[:-1] + (4,), dtype=features.dtype, device=features.device)
    rot_quat[..., 0] = torch.cos(angle)
    rot_quat[..., 2] = torch.sin(angle)

    root = torch.zeros(features.shape[:-1] + (3,), dtype=features.dtype, device=features.device)
    root[..., 1:, 0] = features[..., :-1, 1]
    root[..., 1:, 2] = features[..., :-1, 2]
    root = torch.cumsum(qrot(qinv(rot_quat), root), dim=-2)
    root[..., 1] = features[..., 3]
    return rot_quat, root


@_array_api
def recover_from_ric(features, num_joints: int | None = None, *, positions_only: bool = False):
    """Joint positions (..., T, J, 3) from features (..., T, D).

    Integrates the yaw velocity to a heading per frame and the root velocity to a root path
    (both starting at 0), then un-rotates the root-relative positions and adds the root x/z.
    positions_only: features are only the part the joints are recovered from, (..., T, 4 + 3(J-1))
    (the root and the joint positions; num_joints required); the joints are the same to the bit.
    """
    if positions_only and num_joints is None:
        raise ValueError("recover_from_ric(positions_only=True) needs num_joints")
    num_joints = num_joints or skeleton_for(features.shape[-1]).num_joints
    layout = FeatureLayout(num_joints)
    expected = layout.positions.stop if positions_only else layout.dim
    if features.shape[-1] != expected:
        raise ValueError(
            f"features of width {features.shape[-1]} do not fit {num_joints} joints (expected {expected})"
        )
    rot_quat, root = recover_root_rot_pos(features)
    local = features[..., layout.positions].reshape(features.shape[:-1] + (num_joints - 1, 3))
    local = qrot(qinv(rot_quat)[..., None, :], local)
    local = (
        local
        + torch.stack((root[..., 0], torch.zeros_like(root[..., 0]), root[..., 2]), dim=-1)[..., None, :]
    )
    return torch.cat((root[..., None, :], local), dim=-2)


def features_to_joints(features, num_joints: int | None = None):
    """Alias of `recover_from_ric`: joints (..., T, J, 3) from features (..., T, D)."""
    return recover_from_ric(features, num_joints)


def reference_std(data: np.ndarray, num_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and Std (D,) of stacked frames (N, D) the reference way: Std group-averaged."""
    mean = data.mean(axis=0)
    std = data.std(axis=0)
    for group in FeatureLayout(num_joints).groups():
        std[group] = std[group].mean()
    return mean, std


__all__ = [
    "FeatureLayout",
    "joints_to_features",
    "recover_from_ric",
    "recover_root_rot_pos",
    "features_to_joints",
    "reference_std",
    "T2M_SKELETON",
]


def pad_motions(features, frames: int | None = None) -> np.ndarray:
    """Motions of different lengths (each (T_i, D)) -> (B, frames, D) float32, each cut or
    zero-padded to `frames` (default: the longest). Readers mask the padding by the lengths."""
    features = [np.asarray(f) for f in features]
    frames = max(len(f) for f in features) if frames is None else int(frames)
    out = np.zeros((len(features), frames, features[0].shape[-1]), np.float32)
    for i, f in enumerate(features):
        out[i, : min(len(f), frames)] = f[:frames]
    return out

"""Skeletons of the HumanML3D (22 joints) and KIT-ML (21 joints) formats, with kinematics.

Conventions (motion-format.md): y is up, the body faces +Z at frame 0 and +X is the body's left.
Each joint's rest direction from its parent is an axis-aligned unit vector; the target skeleton
scales those by measured bone lengths.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mmm.motion.quaternion import gaussian_smooth_time, qbetween, qinv, qmul, qrot

_X, _NX, _Y, _NY, _Z = (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Skeleton:
    """A kinematic tree plus the joint roles the feature pipeline needs."""

    name: str
    joint_names: tuple[str, ...]
    kinematic_chains: tuple[tuple[int, ...], ...]
    rest_directions: tuple[tuple[float, float, float], ...]
    # Bone length from each joint's parent (0 for the root) of the target skeleton that
    # joints_to_features retargets to; None keeps each motion's own proportions.
    bone_lengths: tuple[float, ...] | None
    face_joints: tuple[int, int, int, int]  # r_hip, l_hip, r_shoulder, l_shoulder
    left_foot: tuple[int, int]  # ankle, toe: contact channels 0-1
    right_foot: tuple[int, int]  # ankle, toe: contact channels 2-3
    leg_joints: tuple[int, int]  # knee, ankle: their bone lengths set the retargeting scale
    mirror_pairs: tuple[tuple[int, int], ...]
    fps: float
    contact_threshold: float  # squared per-frame displacement below which a foot is planted
    unit_scale: float = 1.0  # metres per unit of the joint coordinates

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def feature_dim(self) -> int:
        k = self.num_joints
        return 4 + (k - 1) * 3 + (k - 1) * 6 + k * 3 + 4

    @property
    def parents(self) -> tuple[int, ...]:
        parents = [-1] * self.num_joints
        for chain in self.kinematic_chains:
            for parent, child in zip(chain[:-1], chain[1:]):
                parents[child] = parent
        return tuple(parents)

    @property
    def mirror_permutation(self) -> tuple[int, ...]:
        perm = list(range(self.num_joints))
        for a, b in self.mirror_pairs:
            perm[a], perm[b] = b, a
        return tuple(perm)

    def offsets(self, lengths: torch.Tensor | None = None, dtype=torch.float64) -> torch.Tensor:
        """Bone vectors (J, 3) in the rest pose: rest direction × length (target lengths by default)."""
        dirs = torch.tensor(self.rest_directions, dtype=dtype)
        if lengths is None:
            if self.bone_lengths is None:
                raise ValueError(f"skeleton {self.name!r} has no target bone lengths; pass lengths")
            lengths = torch.tensor(self.bone_lengths, dtype=dtype)
        return dirs * lengths.to(dtype).unsqueeze(-1)

    def bone_lengths_of(self, joints: torch.Tensor) -> torch.Tensor:
        """Bone lengths (..., J) of a pose (..., J, 3); 0 for the root."""
        parents = torch.tensor(self.parents[1:])
        lengths = (joints[..., 1:, :] - joints[..., parents, :]).norm(dim=-1)
        return torch.cat((torch.zeros_like(lengths[..., :1]), lengths), dim=-1)


def mirror_joints(joints: torch.Tensor, skeleton: Skeleton) -> torch.Tensor:
    """Left/right mirror (..., J, 3): negate x and swap the paired joints."""
    mirrored = joints[..., list(skeleton.mirror_permutation), :].clone()
    mirrored[..., 0] = -mirrored[..., 0]
    return mirrored


def facing_direction(
    joints: torch.Tensor, skeleton: Skeleton, *, swap_hips: bool = False, normalize: bool = True
) -> torch.Tensor:
    """Horizontal facing direction (..., 3) from hips and shoulders of (..., J, 3).

    across = (R_hip - L_hip) + (R_shoulder - L_shoulder), made unit; forward = up × across,
    whose length is the horizontal share of `across` unless `normalize`. The reference inverse
    kinematics swaps the hips (`swap_hips=True`), which shortens the across vector but keeps its
    direction.
    """
    r_hip, l_hip, r_sh, l_sh = skeleton.face_joints
    hips = (
        joints[..., l_hip, :] - joints[..., r_hip, :]
        if swap_hips
        else joints[..., r_hip, :] - joints[..., l_hip, :]
    )
    across = hips + joints[..., r_sh, :] - joints[..., l_sh, :]
    across = across / across.norm(dim=-1, keepdim=True)
    up = across.new_tensor([0.0, 1.0, 0.0]).expand_as(across)
    forward = torch.linalg.cross(up, across, dim=-1)
    return forward / forward.norm(dim=-1, keepdim=True) if normalize else forward


def inverse_kinematics(
    joints: torch.Tensor, skeleton: Skeleton, *, smooth_forward: bool = False
) -> torch.Tensor:
    """Local joint rotations (T, J, 4) from positions (T, J, 3), as the reference pipeline computes them.

    The root rotation turns the (optionally Gaussian-smoothed, sigma 20 frames) facing direction to
    +Z, and is forced to identity at frame 0; each bone's rotation is the shortest arc from its
    rest direction. Reference quirks reproduced on purpose: the facing vector uses swapped hips,
    and every chain, the arms included, starts from the root rotation rather than its parent's.
    """
    # Smoothed before normalizing, as the reference does: tilted frames weigh less.
    forward = facing_direction(joints, skeleton, swap_hips=True, normalize=False)
    if smooth_forward:
        forward = gaussian_smooth_time(forward, 20.0)
    forward = forward / forward.norm(dim=-1, keepdim=True)
    target = forward.new_tensor([0.0, 0.0, 1.0]).expand_as(forward)
    root_quat = qbetween(forward, target).clone()
    root_quat[0] = root_quat.new_tensor([1.0, 0.0, 0.0, 0.0])

    quats = joints.new_zeros(joints.shape[:-1] + (4,))
    quats[..., 0] = 1.0
    quats[:, 0] = root_quat
    rest = torch.tensor(skeleton.rest_directions, dtype=joints.dtype, device=joints.device)
    for chain in skeleton.kinematic_chains:
        R = root_quat
        for parent, child in zip(chain[:-1], chain[1:]):
            bone = joints[:, child] - joints[:, parent]
            rot = qbetween(rest[child].expand_as(bone), bone)
            local = qmul(qinv(R), rot)
            quats[:, child] = local
            R = qmul(R, local)
    return quats


def forward_kinematics(
    quats: torch.Tensor,
    root_pos: torch.Tensor,
    skeleton: Skeleton,
    offsets: torch.Tensor | None = None,
    *,
    chains_from_root: bool = True,
) -> torch.Tensor:
    """Joint positions (..., J, 3) from local rotations (..., J, 4) and root positions (..., 3).

    offsets: (J, 3) or (..., J, 3) bone vectors (target skeleton by default).
    chains_from_root=True follows the reference (every chain starts from the root rotation, the
    inverse of `inverse_kinematics`); False composes rotations along the true parent hierarchy,
    which is what procedural animation wants (arms follow the bending spine).
    """
    if offsets is None:
        offsets = skeleton.offsets(dtype=quats.dtype).to(quats.device)
    joints = [None] * skeleton.num_joints
    global_rot = [None] * skeleton.num_joints
    joints[0] = root_pos
    global_rot[0] = quats[..., 0, :]
    for chain in skeleton.kinematic_chains:
        R = quats[..., 0, :] if chains_from_root else global_rot[chain[0]]
        for parent, child in zip(chain[:-1], chain[1:]):
            R = qmul(R, quats[..., child, :])
            global_rot[child] = R
            joints[child] = qrot(R, offsets[..., child, :]) + joints[parent]
    return torch.stack(joints, dim=-2)


T2M_SKELETON = Skeleton(
    name="t2m",
    joint_names=(
        "pelvis",
        "left_hip",
        "right_hip",
        "spine1",
        "left_knee",
        "right_knee",
        "spine2",
        "left_ankle",
        "right_ankle",
        "spine3",
        "left_foot",
        "right_foot",
        "neck",
        "left_collar",
        "right_collar",
        "head",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_wrist",
        "right_wrist",
    ),
    kinematic_chains=(
        (0, 2, 5, 8, 11),
        (0, 1, 4, 7, 10),
        (0, 3, 6, 9, 12, 15),
        (9, 14, 17, 19, 21),
        (9, 13, 16, 18, 20),
    ),
    rest_directions=(
        (0.0, 0.0, 0.0),
        _X,
        _NX,
        _Y,
        _NY,
        _NY,
        _Y,
        _NY,
        _NY,
        _Y,
        _Z,
        _Z,
        _Y,
        _X,
        _NX,
        _Z,
        _NY,
        _NY,
        _NY,
        _NY,
        _NY,
        _NY,
    ),
    # Measured on ../shared/reference/humanml3d/new_joints/012314.npy (constant to 1e-7 in
    # every frame: the whole dataset is retargeted to this skeleton).
    bone_lengths=(
        0.0,
        0.103074,
        0.109883,
        0.131568,
        0.393623,
        0.390188,
        0.143190,
        0.432433,
        0.425643,
        0.057365,
        0.143382,
        0.149419,
        0.219360,
        0.137487,
        0.143383,
        0.103039,
        0.131614,
        0.122984,
        0.256840,
        0.263092,
        0.266012,
        0.269876,
    ),
    face_joints=(2, 1, 17, 16),
    left_foot=(7, 10),
    right_foot=(8, 11),
    leg_joints=(5, 8),
    mirror_pairs=((1, 2), (4, 5), (7, 8), (10, 11), (13, 14), (16, 17), (18, 19), (20, 21)),
    fps=20.0,
    contact_threshold=0.002,
)

KIT_SKELETON = Skeleton(
    name="kit",
    joint_names=(
        "root",
        "back1",
        "back2",
        "chest",
        "head",
        "right_shoulder",
        "right_elbow",
        "right_wrist",
        "left_shoulder",
        "left_elbow",
        "left_wrist",
        "right_hip",
        "right_knee",
        "right_ankle",
        "right_heel",
        "right_toe",
        "left_hip",
        "left_knee",
        "left_ankle",
        "left_heel",
        "left_toe",
    ),
    kinematic_chains=(
        (0, 11, 12, 13, 14, 15),
        (0, 16, 17, 18, 19, 20),
        (0, 1, 2, 3, 4),
        (3, 5, 6, 7),
        (3, 8, 9, 10),
    ),
    rest_directions=(
        (0.0, 0.0, 0.0),
        _Y,
        _Y,
        _Y,
        _Y,
        _X,
        _NY,
        _NY,
        _NX,
        _NY,
        _NY,
        _X,
        _NY,
        _NY,
        _Z,
        _Z,
        _NX,
        _NY,
        _NY,
        _Z,
        _Z,
    ),
    # KIT's target skeleton is taken from a clip of the dataset itself, which is not
    # redistributable: joints_to_features keeps each motion's proportions.
    bone_lengths=None,
    face_joints=(11, 16, 5, 8),
    left_foot=(19, 20),
    right_foot=(14, 15),
    leg_joints=(17, 18),
    mirror_pairs=((5, 8), (6, 9), (7, 10), (11, 16), (12, 17), (13, 18), (14, 19), (15, 20)),
    fps=12.5,
    # The reference KIT script passes the same 0.002 although its coordinates are millimetres.
    contact_threshold=0.002,
    unit_scale=0.001,
)

SKELETONS = {"t2m": T2M_SKELETON, "humanml3d": T2M_SKELETON, "kit": KIT_SKELETON}


def skeleton_for(num_joints_or_dim: int) -> Skeleton:
    """The skeleton for 22/21 joints or a 263/251-wide feature."""
    for sk in (T2M_SKELETON, KIT_SKELETON):
        if num_joints_or_dim in (sk.num_joints, sk.feature_dim):
            return sk
    raise ValueError(
        f"no skeleton with {num_joints_or_dim} joints or feature dims: expected 22 joints / 263 dims "
        "(HumanML3D) or 21 joints / 251 dims (KIT-ML)"
    )

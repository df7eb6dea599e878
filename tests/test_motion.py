"""Motion representation: skeletons, rotations, joints <-> 263-d features against the reference data."""

import math

import numpy as np
import pytest
import torch

from mmm.motion.features import FeatureLayout, joints_to_features, recover_from_ric
from mmm.motion.quaternion import (
    cont6d_to_matrix,
    gaussian_smooth_time,
    qbetween,
    qmul,
    qrot,
    quat_about_y,
    quat_to_cont6d,
    quat_to_matrix,
    yaw_of,
)
from mmm.motion.skeleton import KIT_SKELETON, T2M_SKELETON, forward_kinematics, mirror_joints, skeleton_for
from tests.conftest import REFERENCE
from tests.helpers import turning_walker


def random_quats(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=torch.float64)
    return q / q.norm(dim=-1, keepdim=True)


def test_qrot_matches_rotation_matrix_and_composition():
    q, r = random_quats(50, 0), random_quats(50, 1)
    v = torch.randn(50, 3, dtype=torch.float64)
    assert torch.allclose(qrot(q, v), (quat_to_matrix(q) @ v.unsqueeze(-1)).squeeze(-1), atol=1e-12)
    assert torch.allclose(qrot(qmul(q, r), v), qrot(q, qrot(r, v)), atol=1e-12)
    assert torch.allclose(cont6d_to_matrix(quat_to_cont6d(q)), quat_to_matrix(q), atol=1e-12)


def test_qbetween_and_yaw():
    v0, v1 = torch.randn(20, 3, dtype=torch.float64), torch.randn(20, 3, dtype=torch.float64)
    rotated = qrot(qbetween(v0, v1), v0)
    assert torch.allclose(
        rotated / rotated.norm(dim=-1, keepdim=True), v1 / v1.norm(dim=-1, keepdim=True), atol=1e-10
    )
    # Positive yaw turns +Z towards +X (the body's left): a left turn.
    q = quat_about_y(torch.tensor(math.pi / 2, dtype=torch.float64))
    assert torch.allclose(
        qrot(q, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)),
        torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
        atol=1e-12,
    )
    assert yaw_of(q).item() == pytest.approx(math.pi / 2)


def test_gaussian_smoothing_is_a_normalized_filter_with_edge_replication():
    x = torch.zeros(200, 1, dtype=torch.float64)
    x[100] = 1.0
    y = gaussian_smooth_time(x, 20.0)
    assert y.sum().item() == pytest.approx(1.0, abs=1e-12)
    # Value at the impulse = normalized kernel centre; the kernel of radius 80 sums to 1.
    offsets = torch.arange(-80, 81, dtype=torch.float64)
    kernel = torch.exp(-0.5 * (offsets / 20.0) ** 2)
    assert y[100, 0].item() == pytest.approx((1 / kernel.sum()).item(), rel=1e-12)
    # Edge replication ('nearest'): a step at the start stays constant there.
    z = torch.ones(10, 2, dtype=torch.float64) * 3.0
    assert torch.allclose(gaussian_smooth_time(z, 20.0), z)


def test_skeletons():
    assert T2M_SKELETON.num_joints == 22 and T2M_SKELETON.feature_dim == 263
    assert KIT_SKELETON.num_joints == 21 and KIT_SKELETON.feature_dim == 251
    assert T2M_SKELETON.parents[21] == 19 and T2M_SKELETON.parents[13] == 9 and T2M_SKELETON.parents[10] == 7
    assert skeleton_for(263) is T2M_SKELETON and skeleton_for(21) is KIT_SKELETON
    with pytest.raises(ValueError, match="22 joints / 263"):
        skeleton_for(100)
    # Standing T-pose of the target skeleton: the lowest point (toes are +z of the ankle at the
    # same height) sits about 0.9 m under the pelvis, which the spec gives as standing height.
    rest = forward_kinematics(
        torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(22, 4),
        torch.zeros(3, dtype=torch.float64),
        T2M_SKELETON,
    )
    assert -rest[:, 1].min().item() == pytest.approx(0.103074 * 0 + 0.393623 + 0.432433, abs=0.05)
    assert rest[1, 0] > 0 and rest[2, 0] < 0  # left hip at +X
    assert torch.allclose(
        T2M_SKELETON.bone_lengths_of(rest),
        torch.tensor(T2M_SKELETON.bone_lengths, dtype=torch.float64),
        atol=1e-9,
    )


def test_feature_layout_covers_263_in_seven_groups():
    layout = FeatureLayout(22)
    groups = layout.groups()
    assert layout.dim == 263 and len(groups) == 7
    assert groups[0].start == 0 and groups[-1].stop == 263
    assert all(a.stop == b.start for a, b in zip(groups[:-1], groups[1:]))
    assert (layout.positions.start, layout.positions.stop, layout.rotations.stop, layout.velocities.stop) == (
        4,
        67,
        193,
        259,
    )


@pytest.mark.skipif(REFERENCE is None, reason="../shared/reference not available")
def test_recover_from_ric_reproduces_reference_joints():
    features = np.load(REFERENCE / "humanml3d/new_joint_vecs/012314.npy")
    joints = np.load(REFERENCE / "humanml3d/new_joints/012314.npy")
    recovered = recover_from_ric(features)
    assert recovered.shape == (170, 22, 3) and recovered.dtype == np.float32
    assert np.abs(recovered - joints).max() < 1e-5
    # The torch path, batched, gives the same.
    batch = recover_from_ric(torch.from_numpy(np.stack([features, features])))
    assert batch.shape == (2, 170, 22, 3)
    assert (batch[1].numpy() - joints).__abs__().max() < 1e-5


@pytest.mark.skipif(REFERENCE is None, reason="../shared/reference not available")
def test_the_joints_of_the_position_features_alone_are_those_of_all_263():
    features = torch.from_numpy(np.load(REFERENCE / "humanml3d/new_joint_vecs/012314.npy"))
    positions = features[:, :67].clone()  # root (4) and joints 1..21 relative to it (63)
    assert torch.equal(recover_from_ric(positions, 22, positions_only=True), recover_from_ric(features))
    with pytest.raises(ValueError, match="needs num_joints"):
        recover_from_ric(positions, positions_only=True)
    with pytest.raises(ValueError, match="width 263 do not fit 22 joints \\(expected 67\\)"):
        recover_from_ric(features, 22, positions_only=True)


@pytest.mark.skipif(REFERENCE is None, reason="../shared/reference not available")
def test_joints_to_features_reproduces_reference_features():
    features = np.load(REFERENCE / "humanml3d/new_joint_vecs/012314.npy")
    joints = np.load(REFERENCE / "humanml3d/new_joints/012314.npy")
    ours = joints_to_features(joints, fix_yaw_flip=False)
    assert ours.shape == (169, 263)
    # The reference processed 171 joint frames, of which new_joints keeps 170: the heading is
    # smoothed with a 20-frame sigma (radius 80), so rows far from the end are identical and the
    # last ones differ slightly.
    assert np.abs(ours[:89] - features[:89]).max() < 2e-5
    assert np.abs(ours - features[:169]).max() < 0.02
    assert np.array_equal(ours[:, 259:], features[:169, 259:])  # foot contacts exactly
    # And back to joints: the round trip is exact.
    assert np.abs(recover_from_ric(ours) - joints[:169]).max() < 1e-5


def test_round_trip_on_a_turning_motion_and_the_yaw_flip_quirk():
    joints = turning_walker().numpy()
    features = joints_to_features(joints, retarget=False)
    recovered = recover_from_ric(features)
    # Recovered joints are the input placed in the canonical frame (floor at 0, frame-0 root at
    # the origin, facing +Z), so their features are the same, except within the heading
    # smoothing's reach (80 frames) of the end, one frame shorter now.
    canon = joints_to_features(recovered, retarget=False)
    assert np.abs(canon[:75] - features[:75]).max() < 1e-6
    # Shape is preserved frame by frame (bone lengths and the pairwise distances).
    d_in = np.linalg.norm(joints[:-1, :, None] - joints[:-1, None], axis=-1)
    d_out = np.linalg.norm(recovered[:, :, None] - recovered[:, None], axis=-1)
    assert np.abs(d_in - d_out).max() < 1e-6
    # The path closes the same way: total heading change and root path length survive.
    path_in = np.linalg.norm(np.diff(joints[:-1, 0, [0, 2]], axis=0), axis=-1).sum()
    path_out = np.linalg.norm(np.diff(recovered[:, 0, [0, 2]], axis=0), axis=-1).sum()
    assert path_out == pytest.approx(path_in, rel=1e-6)
    # The reference's yaw flip: when the heading crosses 180 degrees one frame's yaw velocity
    # changes sign and the recovered body drifts; fixed by default.
    quirky = joints_to_features(joints, retarget=False, fix_yaw_flip=False)
    flipped = np.flatnonzero(np.sign(quirky[:, 0]) != np.sign(features[:, 0]))
    assert len(flipped) >= 1
    recovered_quirky = recover_from_ric(quirky)
    assert np.abs(recovered_quirky - recovered).max() > 0.1


@pytest.mark.slow
def test_features_are_invariant_to_placement_and_scale():
    joints = turning_walker(turns=0.3).numpy()
    base = joints_to_features(joints)
    yaw = quat_about_y(torch.tensor(1.1, dtype=torch.float64)).numpy()
    moved = qrot(torch.from_numpy(yaw), torch.from_numpy(joints)).numpy() + np.array([3.0, 0.4, -2.0])
    assert np.abs(joints_to_features(moved) - base).max() < 1e-6
    # A bigger person is retargeted to the target skeleton by leg length.
    assert np.abs(joints_to_features(joints * 1.2) - base).max() < 1e-6
    # Without retargeting, the scale shows in the root height.
    assert joints_to_features(joints * 1.2, retarget=False)[0, 3] == pytest.approx(base[0, 3] * 1.2, rel=1e-6)


def test_mirror_twice_is_identity_and_swaps_sides():
    joints = torch.from_numpy(turning_walker(frames=30).numpy())
    mirrored = mirror_joints(joints, T2M_SKELETON)
    assert torch.allclose(mirror_joints(mirrored, T2M_SKELETON), joints)
    assert torch.allclose(mirrored[:, 1, 0], -joints[:, 2, 0])  # new left hip = old right hip, x negated


def test_numpy_and_torch_paths_agree_and_check_shapes():
    joints = turning_walker(frames=50).numpy().astype(np.float32)
    np_feat = joints_to_features(joints)
    torch_feat = joints_to_features(torch.from_numpy(joints).double())
    assert np_feat.dtype == np.float32 and torch_feat.dtype == torch.float64
    assert np.abs(np_feat - torch_feat.numpy()).max() < 1e-5
    with pytest.raises(ValueError, match=r"\(T, J, 3\)"):
        joints_to_features(np.zeros((10, 22)))
    with pytest.raises(ValueError, match="width 200"):
        recover_from_ric(np.zeros((10, 200)), 22)

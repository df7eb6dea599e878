"""BVH export (mmm.export.bvh): round trips through the parser, rigidification, file structure, errors."""

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from mmm.export import (
    BVHInfo,
    bvh_joint_names,
    euler_to_matrix,
    features_to_bvh,
    matrix_to_euler_zxy,
    read_bvh,
    write_bvh,
)
from mmm.motion.quaternion import qmul, quat_about_y, quat_from_axis_angle, quat_to_matrix
from mmm.motion.skeleton import KIT_SKELETON, T2M_SKELETON, forward_kinematics

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "reference"
REFERENCE_MOTION = REFERENCE / "humanml3d" / "new_joints" / "012314.npy"
T2M_CARRIERS = (
    "pelvis_to_left_hip",
    "pelvis_to_right_hip",
    "pelvis_to_spine1",
    "spine3_to_neck",
    "spine3_to_left_collar",
    "spine3_to_right_collar",
)
TOL = 1e-3  # metres: the round trip must reproduce every joint within 1 mm


def reference_joints() -> np.ndarray:
    if not REFERENCE_MOTION.is_file():
        pytest.skip(f"{REFERENCE_MOTION} not available (../shared/reference missing)")
    return np.load(REFERENCE_MOTION)


def max_error(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=-1).max())


def axis_angle(axis, angle):
    angle = torch.as_tensor(angle, dtype=torch.float64)
    axis = torch.tensor(axis, dtype=torch.float64).expand(angle.shape + (3,))
    return quat_from_axis_angle(axis, angle)


def turning_motion(T: int = 61) -> np.ndarray:
    """T2M joints (T, 22, 3): turns 0 -> 180 degrees about +Y while walking forward, raises the left
    arm forward through horizontal to straight overhead, the right arm sideways to overhead, kicks
    the right thigh forward through horizontal (at s = 0.75: a hip rotation of -90 degrees about X,
    the Z-X-Y gimbal lock) and bends the spine, elbows and knee.

    quats[c] is the local rotation of the bone parent(c) -> c (forward_kinematics' convention).
    """
    s = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    quats = torch.zeros(T, 22, 4, dtype=torch.float64)
    quats[..., 0] = 1.0
    quats[:, 0] = quat_about_y(math.pi * s)
    quats[:, 3] = axis_angle((1.0, 0.0, 0.0), 0.3 * s)  # spine bends forward
    quats[:, 15] = axis_angle((0.0, 1.0, 0.0), 0.4 * torch.sin(2 * math.pi * s))  # head turns
    quats[:, 18] = axis_angle((1.0, 0.0, 0.0), -math.pi * s)  # left upper arm: down -> forward -> up
    quats[:, 20] = axis_angle((1.0, 0.0, 0.0), -0.6 * s)  # left elbow bends
    quats[:, 19] = axis_angle((0.0, 0.0, 1.0), -math.pi * s)  # right upper arm: down -> sideways -> up
    quats[:, 21] = axis_angle((0.0, 0.0, 1.0), -0.5 * s)  # right elbow bends
    quats[:, 5] = axis_angle((1.0, 0.0, 0.0), -2.0 * math.pi / 3.0 * s)  # right thigh: 0 -> 120 deg forward
    quats[:, 8] = axis_angle((1.0, 0.0, 0.0), 0.8 * s)  # right knee bends
    root = torch.stack((0.4 * s, 0.9 + 0.03 * torch.sin(4 * math.pi * s), 0.8 * s), dim=-1)
    joints = forward_kinematics(quats, root, T2M_SKELETON, chains_from_root=False)
    return joints.numpy()


KIT_LENGTHS_MM = (
    0.0,
    110.0,
    120.0,
    160.0,
    210.0,
    190.0,
    290.0,
    250.0,
    190.0,
    290.0,
    250.0,
    95.0,
    430.0,
    420.0,
    60.0,
    140.0,
    95.0,
    430.0,
    420.0,
    60.0,
    140.0,
)


def kit_motion(T: int = 40) -> np.ndarray:
    """KIT-ML joints (T, 21, 3) in millimetres: walks and turns 90 degrees, legs and arms swing."""
    s = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    swing = torch.sin(4 * math.pi * s)
    quats = torch.zeros(T, 21, 4, dtype=torch.float64)
    quats[..., 0] = 1.0
    quats[:, 0] = quat_about_y(0.5 * math.pi * s)
    quats[:, 12] = axis_angle((1.0, 0.0, 0.0), 0.5 * swing)  # hips swing (joint 12 = right knee's bone)
    quats[:, 17] = axis_angle((1.0, 0.0, 0.0), -0.5 * swing)
    quats[:, 13] = axis_angle((1.0, 0.0, 0.0), 0.4 * (1 + swing))
    quats[:, 6] = axis_angle((1.0, 0.0, 0.0), -0.6 * swing)  # arms swing
    quats[:, 9] = axis_angle((1.0, 0.0, 0.0), 0.6 * swing)
    quats[:, 7] = axis_angle((0.0, 0.0, 1.0), 0.3 * s)
    quats[:, 2] = qmul(axis_angle((1.0, 0.0, 0.0), 0.2 * s), axis_angle((0.0, 1.0, 0.0), 0.3 * swing))
    root = torch.stack((300.0 * s, 1000.0 + 20.0 * swing, 1200.0 * s), dim=-1)
    offsets = KIT_SKELETON.offsets(torch.tensor(KIT_LENGTHS_MM, dtype=torch.float64))
    return forward_kinematics(quats, root, KIT_SKELETON, offsets, chains_from_root=False).numpy()


def noisy_lengths(joints: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """The same bone directions with every bone's length scaled by (1 + sigma·N(0,1)) per frame."""
    rng = np.random.default_rng(seed)
    scale = 1.0 + sigma * rng.standard_normal(joints.shape[:2])
    out = joints.astype(np.float64).copy()
    parents = T2M_SKELETON.parents
    for j in range(1, joints.shape[1]):  # parents precede children in this skeleton
        out[:, j] = out[:, parents[j]] + (joints[:, j] - joints[:, parents[j]]) * scale[:, j, None]
    return out


def rigidified(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median bone lengths (J,) and the motion with every bone at its median length (T, J, 3)."""
    parents = T2M_SKELETON.parents
    lengths = np.zeros(joints.shape[1])
    out = joints.copy()
    for j in range(1, joints.shape[1]):
        bone = joints[:, j] - joints[:, parents[j]]
        norm = np.linalg.norm(bone, axis=-1, keepdims=True)
        lengths[j] = np.median(norm)
        out[:, j] = out[:, parents[j]] + lengths[j] * bone / norm
    return lengths, out


# --------------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------------


def test_reference_motion_round_trip(tmp_path):
    joints = reference_joints()
    info = write_bvh(joints, tmp_path / "ref.bvh")
    motion = read_bvh(tmp_path / "ref.bvh")
    parsed = motion.positions(T2M_SKELETON.joint_names)
    err = max_error(parsed, joints)
    print(f"reference 012314 round trip: max joint error {err * 1e3:.6f} mm over {len(joints)} frames")
    assert err < TOL
    assert parsed.shape == joints.shape
    # Its bone lengths are constant: rigidifying changes nothing measurable.
    assert info.max_deviation_m < 1e-5
    np.testing.assert_allclose(info.bone_lengths, T2M_SKELETON.bone_lengths, atol=1e-5)
    # The whole pelvis path is in the root's position channels, in metres.
    np.testing.assert_allclose(motion.motion[:, :3], joints[:, 0], atol=1e-6)
    assert motion.fps == 20.0 and motion.num_frames == len(joints)


def test_features_to_bvh_matches_recovered_joints(tmp_path):
    features_file = REFERENCE / "humanml3d" / "new_joint_vecs" / "012314.npy"
    joints = reference_joints()
    if not features_file.is_file():
        pytest.skip(f"{features_file} not available")
    info = features_to_bvh(np.load(features_file), tmp_path / "f.bvh")
    parsed = read_bvh(tmp_path / "f.bvh").positions(T2M_SKELETON.joint_names)
    assert info.num_frames == len(joints)
    assert max_error(parsed, joints) < TOL


def local_rotation_steps(motion) -> np.ndarray:
    """Angle in degrees (T-1, N) between consecutive frames' local rotations of every BVH joint."""
    R = euler_to_matrix(np.radians(motion.motion[:, 3:].reshape(motion.num_frames, -1, 3)), "ZXY")
    rel = np.einsum("tnji,tnjk->tnik", R[:-1], R[1:])
    return np.degrees(np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("arcs", ["parent", "heading", "world"])
def test_turning_motion_with_arms_overhead_round_trip(tmp_path, arcs):
    T = 61
    joints = turning_motion(T)
    s = np.linspace(0.0, 1.0, T)
    # The construction really does what the test needs: a half turn, arms overhead at the end.
    across = joints[:, 2] - joints[:, 1]  # right hip - left hip points to -X at the start, +X at the end
    assert across[0, 0] < -0.2 and across[-1, 0] > 0.2
    for shoulder, wrist in ((16, 20), (17, 21)):
        assert joints[-1, wrist, 1] - joints[-1, shoulder, 1] > 0.45
    info = write_bvh(joints, tmp_path / "turn.bvh", arcs=arcs)
    motion = read_bvh(tmp_path / "turn.bvh")
    err = max_error(motion.positions(T2M_SKELETON.joint_names), joints)
    print(f"turning/arms-overhead round trip (arcs={arcs}): max joint error {err * 1e3:.6f} mm")
    assert err < TOL
    assert info.max_deviation_m < 1e-9  # built with rigid bones

    def channel(joint, name):
        return motion.motion[:, motion.channel_index(joint, name)]

    # The root channel is the heading from hips and shoulders, continuous through 180 degrees.
    r_hip, l_hip, r_sh, l_sh = T2M_SKELETON.face_joints
    a = joints[:, r_hip] - joints[:, l_hip] + joints[:, r_sh] - joints[:, l_sh]
    heading = np.degrees(np.unwrap(np.arctan2(a[:, 2], -a[:, 0])))
    np.testing.assert_allclose(channel("pelvis", "Yrotation"), heading, atol=1e-4)
    assert heading[-1] > 179.0
    # End Sites extend the leaf bones: the left hand's tip is 5 cm beyond the wrist, overhead.
    left_tip = motion.end_positions[:, list(motion.end_sites).index("left_wrist")]
    forearm = joints[-1, 20] - joints[-1, 18]
    np.testing.assert_allclose(
        left_tip[-1] - joints[-1, 20], 0.05 * forearm / np.linalg.norm(forearm), atol=1e-5
    )
    if arcs != "parent":
        return
    # Arcs taken in the parent's frame give back the construction's own angles (R = Rz.Rx.Ry):
    # the thigh's swing about X passes -90 degrees (gimbal lock) at s = 0.75, the arms' to -180.
    np.testing.assert_allclose(channel("right_hip", "Xrotation"), -120.0 * s, atol=1e-4)
    assert abs(np.cos(np.radians(channel("right_hip", "Xrotation")[45]))) < 1e-6
    np.testing.assert_allclose(channel("left_shoulder", "Xrotation")[:-1], -180.0 * s[:-1], atol=1e-4)
    np.testing.assert_allclose(channel("right_shoulder", "Zrotation")[:-1], -180.0 * s[:-1], atol=1e-4)
    # ... and an animation without flips: the true motion turns each joint by at most 3 degrees
    # a frame (the last frame's straight-overhead arm has no defined twist).
    assert local_rotation_steps(motion)[:-1].max() < 3.5


def test_kit_motion_round_trip_in_metres(tmp_path):
    joints_mm = kit_motion()
    info = write_bvh(joints_mm, tmp_path / "kit.bvh")  # 21 joints: KIT, 12.5 fps, millimetres
    motion = read_bvh(tmp_path / "kit.bvh")
    err = max_error(motion.positions(KIT_SKELETON.joint_names), joints_mm * KIT_SKELETON.unit_scale)
    print(f"KIT round trip: max joint error {err * 1e3:.6f} mm")
    assert err < TOL
    assert info.skeleton == "kit" and info.fps == 12.5 and motion.fps == 12.5
    assert info.max_deviation_m < 1e-9
    np.testing.assert_allclose(info.bone_lengths, np.array(KIT_LENGTHS_MM) / 1000.0, atol=1e-9)
    assert {
        "root_to_back1",
        "root_to_right_hip",
        "root_to_left_hip",
        "chest_to_head",
        "chest_to_right_shoulder",
        "chest_to_left_shoulder",
    } <= set(motion.names)
    assert len(motion.names) == 21 + 6
    # Offsets are written in metres: the thigh bone is 0.43 m, not 430.
    assert motion.offsets[motion.names.index("right_knee")] == pytest.approx([0.0, -0.43, 0.0], abs=1e-9)


def test_non_rigid_motion_is_rigidified_and_the_deviation_reported(tmp_path):
    joints = reference_joints()
    noisy = noisy_lengths(joints, sigma=0.03, seed=7)
    lengths, expected = rigidified(noisy)
    deviation = np.linalg.norm(expected - noisy, axis=-1)
    info = write_bvh(noisy, tmp_path / "noisy.bvh")
    parsed = read_bvh(tmp_path / "noisy.bvh").positions(T2M_SKELETON.joint_names)
    err = max_error(parsed, expected)
    print(
        f"rigidified round trip: max joint error {err * 1e3:.6f} mm; "
        f"reported deviation {info.max_deviation_m * 1e3:.3f} mm"
    )
    assert err < TOL
    np.testing.assert_allclose(info.bone_lengths, lengths, atol=1e-12)
    np.testing.assert_allclose(info.rigid_joints, expected, atol=1e-9)
    assert info.max_deviation_m == pytest.approx(deviation.max(), abs=1e-9)
    assert info.mean_deviation_m == pytest.approx(deviation.mean(), abs=1e-9)
    frame, joint = np.unravel_index(deviation.argmax(), deviation.shape)
    assert (info.max_deviation_frame, info.max_deviation_joint) == (frame, T2M_SKELETON.joint_names[joint])
    # The noise is real (centimetres) and the file does not carry it: its bones are rigid.
    assert info.max_deviation_m > 0.01
    assert max_error(parsed, noisy) == pytest.approx(info.max_deviation_m, abs=1e-5)
    parsed_lengths = T2M_SKELETON.bone_lengths_of(torch.from_numpy(parsed)).numpy()
    assert np.ptp(parsed_lengths, axis=0).max() < 1e-5
    assert info.as_dict()["max_deviation_m"] == info.max_deviation_m


# --------------------------------------------------------------------------------------------
# Euler angles
# --------------------------------------------------------------------------------------------


def test_zxy_euler_conversion_exact_including_gimbal_lock():
    rng = np.random.default_rng(0)
    q = rng.standard_normal((500, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    random = quat_to_matrix(torch.from_numpy(q)).numpy()
    # At and next to the lock (x = +-90 degrees) with arbitrary z and y.
    angles = rng.uniform(-math.pi, math.pi, (200, 3))
    angles[:100, 1] = rng.choice([-0.5 * math.pi, 0.5 * math.pi], 100)
    angles[100:, 1] = np.sign(rng.uniform(-1, 1, 100)) * (0.5 * math.pi - 10.0 ** rng.uniform(-12, -3, 100))
    near_lock = euler_to_matrix(angles, "ZXY")
    for R in (random, near_lock):
        back = euler_to_matrix(matrix_to_euler_zxy(R), "ZXY")
        assert np.abs(back - R).max() < 1e-12
    # R = Rz . Rx . Ry: rotating +Y by (z=90, x=0, y=anything) gives -X; x in [-90, 90].
    R = euler_to_matrix(np.array([math.pi / 2, 0.0, 0.7]), "ZXY")
    np.testing.assert_allclose(R @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(matrix_to_euler_zxy(R), [math.pi / 2, 0.0, 0.7], atol=1e-12)
    assert np.abs(matrix_to_euler_zxy(random)[:, 1]).max() <= math.pi / 2 + 1e-12
    # At the exact lock the y angle is 0 and z carries the combined turn.
    locked = matrix_to_euler_zxy(euler_to_matrix(np.array([0.3, math.pi / 2, 0.5]), "ZXY"))
    np.testing.assert_allclose(locked, [0.8, math.pi / 2, 0.0], atol=1e-9)


# --------------------------------------------------------------------------------------------
# The file
# --------------------------------------------------------------------------------------------


def test_file_structure(tmp_path):
    joints = turning_motion(T=7)
    path = tmp_path / "sub" / "dir" / "s.bvh"
    info = write_bvh(joints, path, fps=30.0)
    assert isinstance(info, BVHInfo) and info.path == path
    text = path.read_text()
    lines = text.splitlines()
    assert lines[0] == "HIERARCHY" and lines[1] == "ROOT pelvis"
    names = re.findall(r"^\s*(?:ROOT|JOINT) (\S+)$", text, flags=re.MULTILINE)
    assert len(names) == 22 + 6 == info.num_joints
    assert set(names) == set(T2M_SKELETON.joint_names) | set(T2M_CARRIERS)
    assert tuple(names) == info.joint_names == bvh_joint_names(T2M_SKELETON)
    channels = re.findall(r"^\s*CHANNELS (\d+) (.*)$", text, flags=re.MULTILINE)
    assert channels[0] == ("6", "Xposition Yposition Zposition Zrotation Xrotation Yrotation")
    assert all(c == ("3", "Zrotation Xrotation Yrotation") for c in channels[1:])
    assert text.count("End Site") == 5  # feet, head, wrists
    assert info.num_channels == 6 + 3 * (28 - 1) == 87
    motion_at = lines.index("MOTION")
    assert lines[motion_at + 1] == "Frames: 7"
    assert float(lines[motion_at + 2].split(":")[1]) == pytest.approx(1 / 30.0, rel=1e-9)
    frame_lines = lines[motion_at + 3 :]
    assert len(frame_lines) == 7
    assert all(len(line.split()) == 87 for line in frame_lines)
    assert text.count("{") == text.count("}") == 28 + 5
    motion = read_bvh(path)
    assert motion.fps == 30.0 and motion.num_frames == 7 and motion.names == info.joint_names
    assert set(motion.end_sites) == {"left_foot", "right_foot", "head", "left_wrist", "right_wrist"}
    # Carriers sit at their joint (zero offset) and orient one bone each; the bone's child joint
    # has the rest direction times the bone length as OFFSET.
    for name in T2M_CARRIERS:
        i = motion.names.index(name)
        assert np.all(motion.offsets[i] == 0.0)
        child = motion.names[motion.parents.index(i)]
        assert name.endswith("_to_" + child)
    for j, name in enumerate(T2M_SKELETON.joint_names[1:], start=1):
        expected = np.array(T2M_SKELETON.rest_directions[j]) * info.bone_lengths[j]
        np.testing.assert_allclose(motion.offsets[motion.names.index(name)], expected, atol=1e-6)
    assert motion.parents[motion.names.index("left_knee")] == motion.names.index("left_hip")
    assert motion.names[motion.parents[motion.names.index("left_hip")]] == "pelvis_to_left_hip"
    # Atomic write: nothing but the file is left in the folder, with a plain file's permissions.
    assert [p.name for p in path.parent.iterdir()] == ["s.bvh"]
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    assert path.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777


def test_truncated_or_corrupt_files_raise_clear_errors(tmp_path):
    path = tmp_path / "ok.bvh"
    write_bvh(turning_motion(T=5), path)
    lines = path.read_text().splitlines()
    motion_at = lines.index("MOTION")

    def broken(name, new_lines):
        p = tmp_path / name
        p.write_text("\n".join(new_lines) + "\n")
        return p

    with pytest.raises(ValueError, match=r"truncated.*declares 5 frames but only 3"):
        read_bvh(broken("short.bvh", lines[:-2]))
    with pytest.raises(ValueError, match="no MOTION section"):
        read_bvh(broken("cut.bvh", lines[: motion_at // 2]))
    with pytest.raises(ValueError, match="hierarchy ended"):
        read_bvh(broken("unclosed.bvh", lines[:20] + lines[motion_at:]))
    wrong = list(lines)
    wrong[motion_at + 4] = " ".join(wrong[motion_at + 4].split()[:-1])
    with pytest.raises(
        ValueError, match=rf"line {motion_at + 5} \(frame 1\) has 86 values, expected 87"
    ) as err:
        read_bvh(broken("wrong.bvh", wrong))
    assert "wrong.bvh" in str(err.value)
    with pytest.raises(ValueError, match="more frame lines"):
        read_bvh(broken("extra.bvh", lines + [lines[-1]]))
    garbled = list(lines)
    garbled[motion_at + 1] = "Frames: many"
    with pytest.raises(ValueError, match="not numbers"):
        read_bvh(broken("garbled.bvh", garbled))
    assert read_bvh(path).num_frames == 5


def test_bad_input_raises_and_leaves_files_alone(tmp_path):
    path = tmp_path / "m.bvh"
    good = turning_motion(T=4)
    write_bvh(good, path)
    before = path.read_text()
    nan = good.copy()
    nan[2, 5, 1] = np.nan
    with pytest.raises(ValueError, match=r"m\.bvh.*NaN.*first: \[2\]"):
        write_bvh(nan, path)
    with pytest.raises(ValueError, match=r"shape \(T, J, 3\), got \(4, 66\)"):
        write_bvh(good.reshape(4, 66), path)
    with pytest.raises(ValueError, match=r"no frames, shape \(0, 22, 3\)"):
        write_bvh(np.zeros((0, 22, 3)), path)
    with pytest.raises(ValueError, match="22 joints / 263 dims"):
        write_bvh(np.zeros((3, 20, 3)), path)
    with pytest.raises(ValueError, match="has 21"):
        write_bvh(good, path, skeleton=KIT_SKELETON)
    with pytest.raises(ValueError, match="fps must be a positive"):
        write_bvh(good, path, fps=0)
    assert path.read_text() == before  # the previous file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.bvh"]
    # A torch tensor and a 1-frame motion are fine.
    info = write_bvh(torch.from_numpy(good[:1]), tmp_path / "one.bvh")
    assert info.num_frames == 1
    assert max_error(read_bvh(tmp_path / "one.bvh").positions(T2M_SKELETON.joint_names), good[:1]) < TOL


def test_independent_bvh_reader_agrees(tmp_path):
    """The pure-Python `bvh` package (not a project dependency) reads the same frames and channels."""
    bvh = pytest.importorskip("bvh")
    path = tmp_path / "turn.bvh"
    write_bvh(turning_motion(T=9), path)
    mine = read_bvh(path)
    theirs = bvh.Bvh(path.read_text())
    assert theirs.nframes == 9 and theirs.frame_time == pytest.approx(mine.frame_time)
    assert tuple(theirs.get_joints_names()) == mine.names
    values = np.array(
        [
            [
                v
                for name in mine.names
                for v in theirs.frame_joint_channels(t, name, theirs.joint_channels(name))
            ]
            for t in range(theirs.nframes)
        ]
    )
    np.testing.assert_array_equal(values, mine.motion)

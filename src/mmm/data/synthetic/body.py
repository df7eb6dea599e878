"""The body model of the procedural animation: the 22-joint skeleton at 20 fps and its kinematics.

Holds the constants of the skeleton and body (bone lengths, hip tilt, neutral foot pitch), small
geometry helpers (rotations about the axes, rotation matrices to quaternions, frames from a
direction and a hint), the per-clip person (`Style`), the hand-over between the parts of a clip
(`State`) and the per-frame animation controls (`Track`, with standing, blending and
concatenation), and the kinematics that turn a track into joint rotations and positions (two-bone
leg IK, the reach of the stance legs, the roll of a planted foot over heel and toe).

A motion is a `Track`: per frame, the pelvis position and heading, a few body angles (pelvis,
spine, neck), arm angles in the chest frame, and for each leg an ankle target with the foot's
pitch and yaw. `track_to_joints` turns it into local joint rotations (legs by analytic two-bone
IK, everything else by composing the angles along the hierarchy) and runs the package's forward
kinematics (`chains_from_root=False`, the true hierarchy) on the target skeleton.

Conventions (motion-format.md): y up, metres, heading angle 0 faces +Z and grows turning left
(+Z towards +X); +X is the body's left. Side index 0 is the left side, 1 the right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
import torch

from mmm.data.synthetic.constants import HIP_DROP, NEUTRAL_FOOT_PITCH, STANDING_HEIGHT
from mmm.data.synthetic.curves import smoothstep
from mmm.motion.skeleton import T2M_SKELETON, forward_kinematics

GRAVITY = 9.81  # m/s^2, for flight phases (running, jumps)
SKELETON = T2M_SKELETON
_BONES = np.asarray(SKELETON.bone_lengths, dtype=np.float64)
_OFFSETS = SKELETON.offsets(dtype=torch.float64).numpy()
_PARENTS = SKELETON.parents
SIGN = np.array([1.0, -1.0])  # x direction of each side: left is +X
HIP_OFFSET = np.array([_BONES[1], _BONES[2]]) * math.cos(HIP_DROP)  # lateral part of pelvis->hip
THIGH = np.array([_BONES[4], _BONES[5]])
SHIN = np.array([_BONES[7], _BONES[8]])
FOOT = np.array([_BONES[10], _BONES[11]])
LEG = THIGH + SHIN
P0 = NEUTRAL_FOOT_PITCH
ANKLE_HEIGHT = FOOT * math.sin(P0)  # flat-foot ankle height with the toe joint on the floor
UP = np.array([0.0, 1.0, 0.0])


# ----------------------------------------------------------------------------- geometry helpers


def wrap_angle(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def rot_x(a):
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    m[..., 0, 0] = 1.0
    m[..., 1, 1], m[..., 1, 2], m[..., 2, 1], m[..., 2, 2] = c, -s, s, c
    return m


def rot_y(a):
    """Rotation about +Y; positive angles turn +Z towards +X (a left turn)."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    m[..., 1, 1] = 1.0
    m[..., 0, 0], m[..., 0, 2], m[..., 2, 0], m[..., 2, 2] = c, s, -s, c
    return m


def rot_z(a):
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    m[..., 2, 2] = 1.0
    m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1] = c, -s, s, c
    return m


def _cross(a, b):
    """Cross product over the last axis (faster than np.cross on small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


def normalize(v, eps=1e-12):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), eps)


def _frame_y_z(y_axis: np.ndarray, z_hint: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) with columns x, y, z: y given, z from a hint orthogonalized."""
    y = normalize(y_axis)
    z = z_hint - (z_hint * y).sum(-1, keepdims=True) * y
    z = normalize(z)
    x = _cross(y, z)
    return np.stack((x, y, z), axis=-1)


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) (w, x, y, z) of rotation matrices (..., 3, 3) (Shepperd's method)."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    choice = np.argmax(np.stack((tr, m00, m11, m22), axis=-1), axis=-1)
    q = np.empty(m.shape[:-2] + (4,))
    diag = np.stack((tr, m00 - m11 - m22, m11 - m00 - m22, m22 - m00 - m11), -1)
    s = np.sqrt(np.maximum(1.0 + diag, 1e-12)) * 2.0
    # case 0: w largest
    s0, s1, s2, s3 = s[..., 0], s[..., 1], s[..., 2], s[..., 3]
    c0 = np.stack((0.25 * s0, (m21 - m12) / s0, (m02 - m20) / s0, (m10 - m01) / s0), -1)
    c1 = np.stack(((m21 - m12) / s1, 0.25 * s1, (m01 + m10) / s1, (m02 + m20) / s1), -1)
    c2 = np.stack(((m02 - m20) / s2, (m01 + m10) / s2, 0.25 * s2, (m12 + m21) / s2), -1)
    c3 = np.stack(((m10 - m01) / s3, (m02 + m20) / s3, (m12 + m21) / s3, 0.25 * s3), -1)
    q = np.select([choice[..., None] == k for k in range(4)], [c0, c1, c2, c3])
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    return normalize(q)


def forward_dir(yaw):
    yaw = np.asarray(yaw, dtype=np.float64)
    return np.stack((np.sin(yaw), np.zeros_like(yaw), np.cos(yaw)), axis=-1)


def left_dir(yaw):
    yaw = np.asarray(yaw, dtype=np.float64)
    return np.stack((np.cos(yaw), np.zeros_like(yaw), -np.sin(yaw)), axis=-1)


# ----------------------------------------------------------------------------- style, state, track


@dataclass
class Style:
    """Per-clip person: proportions are fixed by the skeleton, posture and manner vary."""

    arm_fwd: float  # resting upper-arm elevation (rad, forward)
    arm_abd: float  # resting upper-arm abduction (rad)
    elbow: float  # resting elbow flexion (rad)
    lean: float  # spine pitch (rad, forward)
    pelvis_tilt: float
    head_pitch: float
    step_width: float  # ankle offset outside the hip line (m)
    toe_out: float  # foot yaw outwards (rad)
    stand_fwd: float  # pelvis ahead of the ankles when standing (m)
    knee_soft: float  # standing pelvis below the straight-leg height (m)
    arm_swing: float  # gain of the arm swing
    shrug: float
    noise: float  # amplitude of the small smooth noise
    cadence: float  # scales the step period (longer or shorter strides at a given speed)

    @staticmethod
    def sample(rng: np.random.Generator) -> "Style":
        u = rng.uniform
        return Style(
            arm_fwd=u(-0.02, 0.12),
            arm_abd=u(0.1, 0.22),
            elbow=u(0.12, 0.4),
            lean=u(-0.03, 0.1),
            pelvis_tilt=u(0.0, 0.1),
            head_pitch=u(-0.08, 0.15),
            step_width=u(-0.01, 0.035),
            toe_out=u(0.03, 0.2),
            stand_fwd=u(0.0, 0.04),
            knee_soft=u(0.0, 0.015),
            arm_swing=u(0.75, 1.3),
            shrug=u(-0.05, 0.1),
            noise=u(0.5, 1.5),
            cadence=u(0.92, 1.08),
        )

    @property
    def height(self) -> float:
        """Standing pelvis height of this person."""
        return STANDING_HEIGHT - 0.005 - self.knee_soft

    def half_width(self, side: int) -> float:
        """Lateral distance of the flat ankle from the pelvis centre when standing."""
        return HIP_OFFSET[side] + self.step_width


@dataclass
class State:
    """Where a part ends and the next starts: heading and the two planted feet."""

    heading: float
    feet: np.ndarray  # (2, 3) flat-foot ankle positions
    feet_yaw: np.ndarray  # (2,)

    def center(self, style: Style) -> np.ndarray:
        """Neutral pelvis position (x, 0, z) over these feet."""
        fwd, left = forward_dir(self.heading), left_dir(self.heading)
        mid = self.feet.mean(axis=0)
        return mid - left * (style.half_width(0) - style.half_width(1)) / 2 + fwd * style.stand_fwd

    @staticmethod
    def standing_at(center_xz, heading: float, style: Style) -> "State":
        fwd, left = forward_dir(heading), left_dir(heading)
        c = np.array([center_xz[0], 0.0, center_xz[1]])
        feet = np.stack([c + left * SIGN[s] * style.half_width(s) - fwd * style.stand_fwd for s in (0, 1)])
        feet[:, 1] = ANKLE_HEIGHT
        yaw = np.array([heading + style.toe_out, heading - style.toe_out])
        return State(float(heading), feet, yaw)


@dataclass
class Track:
    """Per-frame animation controls of a motion segment (n frames)."""

    root: np.ndarray  # (n, 3) pelvis position
    heading: np.ndarray  # (n,) body heading (rad)
    pelvis: np.ndarray  # (n, 3) pitch (forward), roll (left hip up), twist (yaw relative to heading)
    spine: np.ndarray  # (n, 3) pitch, roll, twist spread over spine1..3
    neck: np.ndarray  # (n, 2) pitch (down), twist
    arm: np.ndarray  # (n, 2, 4) elevation (forward), abduction, horizontal adduction, elbow flexion
    hint: np.ndarray  # (n, 2, 3) direction the forearm bends to, side-local chest frame (x outwards)
    shrug: np.ndarray  # (n, 2)
    ankle: np.ndarray  # (n, 2, 3) ankle targets
    foot_pitch: np.ndarray  # (n, 2) foot bone angle below the horizontal
    foot_yaw: np.ndarray  # (n, 2)
    planted: np.ndarray  # (n, 2) bool

    @property
    def n(self) -> int:
        return self.root.shape[0]


_BLENDED = (
    "root",
    "heading",
    "pelvis",
    "spine",
    "neck",
    "arm",
    "hint",
    "shrug",
    "ankle",
    "foot_pitch",
    "foot_yaw",
)


def standing_track(n: int, state: State, style: Style) -> Track:
    """n frames of the neutral standing pose over the state's feet."""
    c = state.center(style)
    root = np.tile(np.array([c[0], style.height, c[2]]), (n, 1))
    arm = np.tile(np.array([style.arm_fwd, style.arm_abd, 0.0, style.elbow]), (n, 2, 1))
    hint = np.tile(normalize(np.array([-0.15, 0.0, 1.0])), (n, 2, 1))
    return Track(
        root=root,
        heading=np.full(n, state.heading),
        pelvis=np.tile(np.array([style.pelvis_tilt, 0.0, 0.0]), (n, 1)),
        spine=np.tile(np.array([style.lean, 0.0, 0.0]), (n, 1)),
        neck=np.tile(np.array([style.head_pitch, 0.0]), (n, 1)),
        arm=arm,
        hint=hint,
        shrug=np.full((n, 2), style.shrug),
        ankle=np.tile(state.feet, (n, 1, 1)),
        foot_pitch=np.full((n, 2), P0),
        foot_yaw=np.tile(state.feet_yaw, (n, 1)),
        planted=np.ones((n, 2), dtype=bool),
    )


def concat_tracks(a: Track, b: Track, blend: int) -> Track:
    """a then b; b's first `blend` frames are corrected so that the junction is smooth.

    The jump between a's extrapolated next frame and b's first frame is added to b and faded out
    with a minimum-jerk ease (pose blending over a few frames).
    """
    out = {}
    k = max(1, min(blend, b.n - 1))
    fade = 1.0 - smoothstep(np.arange(k) / k)
    for f in fields(Track):
        x, y = getattr(a, f.name), getattr(b, f.name).copy()
        if f.name in _BLENDED:
            nxt = x[-1] + (x[-1] - x[-2]) if x.shape[0] > 1 else x[-1]
            delta = nxt - y[0]
            if f.name == "foot_yaw" or f.name == "heading":
                delta = wrap_angle(delta)
            y[:k] += delta * fade.reshape((k,) + (1,) * (y.ndim - 1))
        out[f.name] = np.concatenate([x, y], axis=0)
    tr = Track(**out)
    tr.hint = normalize(tr.hint)
    return tr


# ----------------------------------------------------------------------------- pose -> joints


_COLLAR = (rot_z(math.radians(72.0)), rot_z(-math.radians(72.0)))  # spine3 -> collar: up and out
_HIP_TILT = (rot_z(-HIP_DROP), rot_z(HIP_DROP))  # pelvis -> hip bones: out and down
_HIP_VECTORS = (_HIP_TILT[0] @ _OFFSETS[1], _HIP_TILT[1] @ _OFFSETS[2])  # in the pelvis frame


def _pelvis_matrix(tr: Track) -> np.ndarray:
    return rot_y(tr.heading + tr.pelvis[:, 2]) @ rot_x(tr.pelvis[:, 0]) @ rot_z(tr.pelvis[:, 1])


def reach_cap(tr: Track, reach: float, root: np.ndarray | None = None) -> np.ndarray:
    """(n,) highest pelvis height at which every planted leg still reaches its ankle target."""
    root = tr.root if root is None else root
    g0 = _pelvis_matrix(tr)
    cap = np.full(tr.n, np.inf)
    for s in (0, 1):
        off = g0 @ _HIP_VECTORS[s]
        hip_xz = root[:, [0, 2]] + off[:, [0, 2]]
        d2 = ((hip_xz - tr.ankle[:, s][:, [0, 2]]) ** 2).sum(-1)
        span = np.sqrt(np.maximum((reach * LEG[s]) ** 2 - d2, 0.0))
        c = tr.ankle[:, s, 1] + span - off[:, 1]
        cap = np.where(tr.planted[:, s], np.minimum(cap, c), cap)
    return cap


def _arm_frames(tr: Track, side: int) -> tuple[np.ndarray, np.ndarray]:
    """Upper-arm and forearm rotations (n, 3, 3) in the chest frame."""
    e, abd, hadd, elbow = (tr.arm[:, side, i] for i in range(4))
    d = np.stack((np.zeros_like(e), -np.cos(e), np.sin(e)), axis=-1)
    d = np.einsum("nij,nj->ni", rot_z(abd), d)
    d = np.einsum("nij,nj->ni", rot_y(-hadd), d)
    hint = tr.hint[:, side].copy()
    if side == 1:  # side-local x points outwards: mirror for the right arm
        d[:, 0] *= -1
        hint[:, 0] *= -1
    upper = _frame_y_z(-d, hint)
    # A hint parallel to the arm leaves the bending plane undefined: fall back to forwards/up.
    bad = np.abs((normalize(hint) * d).sum(-1)) > 0.999
    if bad.any():
        upper[bad] = _frame_y_z(-d[bad], np.where(np.abs(d[bad, 2:3]) > 0.9, UP, np.array([0.0, 0.0, 1.0])))
    fore = upper @ rot_x(-elbow)
    return upper, fore


def two_bone_ik(hip, target, l1, l2, pole):
    """Knee and reached ankle (n, 3) for a leg from hip towards target, knee bending towards pole."""
    d_vec = target - hip
    d = np.linalg.norm(d_vec, axis=-1, keepdims=True)
    u = d_vec / np.maximum(d, 1e-9)
    dc = np.clip(d, abs(l1 - l2) + 1e-4, (l1 + l2) * 0.9999)
    a = (l1 * l1 - l2 * l2 + dc * dc) / (2 * dc)
    h = np.sqrt(np.maximum(l1 * l1 - a * a, 0.0))
    p = pole - (pole * u).sum(-1, keepdims=True) * u
    p = normalize(p)
    knee = hip + a * u + h * p
    return knee, hip + dc * u, p


def foot_ankle(flat, yaw, pitch, side):
    """Ankle position for a foot planted at `flat` (flat-foot ankle) rolled to `pitch`.

    Toe up (pitch < P0): the foot turns about the heel, taken at the ankle. Heel up (pitch > P0):
    it turns about the toe joint, which stays on its spot.
    """
    h = forward_dir(yaw)
    toe = flat + FOOT[side] * (math.cos(P0) * h - math.sin(P0) * UP)
    rolled = toe - FOOT[side] * (np.cos(pitch)[..., None] * h - np.sin(pitch)[..., None] * UP)
    return np.where((pitch > P0)[..., None], rolled, flat)


def track_to_joints(tr: Track) -> np.ndarray:
    """Joint positions (n, 22, 3) of a track: local rotations, then forward kinematics."""
    return pose_to_joints(*track_to_pose(tr))


def pose_to_joints(quats: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Forward kinematics (true hierarchy) on the target skeleton: (..., 22, 4), (..., 3) -> (..., 22, 3).

    Frames are independent, so many clips can go through in one call (concatenated frames).
    """
    joints = forward_kinematics(
        torch.from_numpy(quats), torch.from_numpy(root), SKELETON, chains_from_root=False
    )
    return joints.numpy()


_PARENT_INDEX = np.array(_PARENTS[1:])


def track_to_pose(tr: Track) -> tuple[np.ndarray, np.ndarray]:
    """Local joint rotations (n, 22, 4) (w, x, y, z) and root positions (n, 3) of a track."""
    n = tr.n
    root = tr.root.copy()
    root[:, 1] = np.minimum(root[:, 1], reach_cap(tr, 0.9995))
    # No toe below the floor: lift a foot whose toe would dip under y = 0.
    toe_y = tr.ankle[:, :, 1] - FOOT * np.sin(tr.foot_pitch)
    tr = replace(tr, ankle=tr.ankle.copy())
    tr.ankle[:, :, 1] += np.maximum(-toe_y, 0.0)
    G = np.zeros((n, 22, 3, 3))
    g0 = _pelvis_matrix(tr)
    G[:, 0] = g0
    G[:, 1], G[:, 2] = g0 @ _HIP_TILT[0], g0 @ _HIP_TILT[1]
    # Spine: base curvature (lumbar back, thorax forward), then the controls spread over 3 joints.
    base = {3: -0.2, 6: 0.12, 9: 0.05}
    weight = {3: 0.35, 6: 0.4, 9: 0.25}
    parent = g0
    for j in (3, 6, 9):
        w = weight[j]
        local = rot_x(base[j] + w * tr.spine[:, 0]) @ rot_z(w * tr.spine[:, 1]) @ rot_y(w * tr.spine[:, 2])
        G[:, j] = parent @ local
        parent = G[:, j]
    G[:, 12] = G[:, 9] @ rot_x(0.1 + 0.4 * tr.neck[:, 0]) @ rot_y(0.5 * tr.neck[:, 1])
    G[:, 15] = G[:, 12] @ rot_y(0.5 * tr.neck[:, 1]) @ rot_x(-1.0 + 0.6 * tr.neck[:, 0])
    # Collars point up and out from the chest; shoulders out (raised by the shrug).
    G[:, 13] = G[:, 9] @ _COLLAR[0]
    G[:, 14] = G[:, 9] @ _COLLAR[1]
    G[:, 16] = G[:, 9] @ rot_z(np.pi / 2 + tr.shrug[:, 0])
    G[:, 17] = G[:, 9] @ rot_z(-np.pi / 2 - tr.shrug[:, 1])
    for side, (elbow_j, wrist_j) in enumerate(((18, 20), (19, 21))):
        upper, fore = _arm_frames(tr, side)
        G[:, elbow_j] = G[:, 9] @ upper
        G[:, wrist_j] = G[:, 9] @ fore
    # Legs by two-bone IK; the knee points between the pelvis and the foot forwards, and up when
    # the leg is raised forwards (kicks, sitting).
    hips = np.stack([root + g0 @ _HIP_VECTORS[0], root + g0 @ _HIP_VECTORS[1]], axis=1)
    pelvis_fwd = forward_dir(tr.heading + tr.pelvis[:, 2])
    for side, (knee_j, ankle_j, toe_j) in enumerate(((4, 7, 10), (5, 8, 11))):
        foot_fwd = forward_dir(tr.foot_yaw[:, side])
        mix = normalize(pelvis_fwd + foot_fwd)
        reach_dir = normalize(tr.ankle[:, side] - hips[:, side])
        raise_ = np.maximum((reach_dir * mix).sum(-1, keepdims=True), 0.0)
        pole = mix + 1.5 * raise_ * UP
        knee, ankle, p = two_bone_ik(hips[:, side], tr.ankle[:, side], THIGH[side], SHIN[side], pole)
        thigh = _frame_y_z(hips[:, side] - knee, p)
        shin_y = normalize(knee - ankle)
        shin_x = thigh[..., 0]
        G[:, knee_j] = thigh
        G[:, ankle_j] = np.stack((shin_x, shin_y, _cross(shin_x, shin_y)), axis=-1)
        pitch = tr.foot_pitch[:, side]
        f = np.cos(pitch)[:, None] * foot_fwd + np.sin(-pitch)[:, None] * UP
        x = normalize(_cross(UP, f))
        G[:, toe_j] = np.stack((x, _cross(f, x), f), axis=-1)
    local = np.empty_like(G)
    local[:, 0] = G[:, 0]
    local[:, 1:] = np.swapaxes(G[:, _PARENT_INDEX], -1, -2) @ G[:, 1:]
    return matrix_to_quat(local), root

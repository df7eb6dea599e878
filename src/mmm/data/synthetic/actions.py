"""Procedural animation of the synthetic vocabulary on the 22-joint skeleton at 20 fps.

A motion is a `Track`: per frame, the pelvis position and heading, a few body angles (pelvis,
spine, neck), arm angles in the chest frame, and for each leg an ankle target with the foot's
pitch and yaw. `track_to_joints` turns it into local joint rotations (legs by analytic two-bone
IK, everything else by composing the angles along the hierarchy) and runs the package's forward
kinematics (`chains_from_root=False`, the true hierarchy) on the target skeleton.

Locomotion (walk, run, turn, circle) plans footsteps from the pelvis path: each foot's stance is
centred on a time of the gait cycle and its foothold is the pelvis pose at that time plus the
foot's offset, so a planted foot never moves; the foot rolls over the heel and the toe joint
(heel strike, flat, heel off), swings to the next foothold, and the pelvis height comes from the
legs: as high as the nominal height allows and never higher than the stance legs reach (which
makes it bob with the gait). Running adds flight phases. Arms swing opposite to the legs, the
pelvis and thorax counter-rotate.

Conventions (motion-format.md): y up, metres, heading angle 0 faces +Z and grows turning left
(+Z towards +X); +X is the body's left. Side index 0 is the left side, 1 the right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
import torch

from mmm.data.synthetic.adherence import HIP_DROP, NEUTRAL_FOOT_PITCH, STANDING_HEIGHT, WALK_SPEEDS
from mmm.motion.skeleton import T2M_SKELETON, forward_kinematics

FPS = 20.0
GRAVITY = 9.81
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
_UP = np.array([0.0, 1.0, 0.0])


class Infeasible(Exception):
    """The requested action cannot be animated in the given number of frames."""


# ----------------------------------------------------------------------------- math helpers


def smoothstep(x):
    """Minimum-jerk ease 0 -> 1 on [0, 1] (clipped outside)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (x * 6.0 - 15.0) + 10.0)


def keyframes(t: np.ndarray, times, values) -> np.ndarray:
    """Piecewise minimum-jerk interpolation through keys (zero velocity at each key); values (K, ...)."""
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    idx = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    t0, t1 = times[idx], times[idx + 1]
    u = smoothstep((t - t0) / np.maximum(t1 - t0, 1e-9))
    u = u.reshape(u.shape + (1,) * (values.ndim - 1))
    return values[idx] + (values[idx + 1] - values[idx]) * u


def hermite(t: np.ndarray, times, values, slopes) -> np.ndarray:
    """Piecewise cubic Hermite through (time, value, slope) knots; constant outside."""
    times, values, slopes = (np.asarray(a, dtype=np.float64) for a in (times, values, slopes))
    idx = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    h = np.maximum(times[idx + 1] - times[idx], 1e-9)
    u = np.clip((t - times[idx]) / h, 0.0, 1.0)
    u2, u3 = u * u, u * u * u
    out = ((2 * u3 - 3 * u2 + 1) * values[idx] + (u3 - 2 * u2 + u) * h * slopes[idx]
           + (-2 * u3 + 3 * u2) * values[idx + 1] + (u3 - u2) * h * slopes[idx + 1])
    out = np.where(t < times[0], values[0], out)
    return np.where(t > times[-1], values[-1], out)


def gaussian_smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian filter along axis 0 with edge replication."""
    if sigma <= 0:
        return x.copy()
    radius = int(3.0 * sigma + 0.5)
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    k /= k.sum()
    pad = np.concatenate([np.repeat(x[:1], radius, axis=0), x, np.repeat(x[-1:], radius, axis=0)], axis=0)
    flat = pad.reshape(pad.shape[0], -1)
    out = np.stack([np.convolve(flat[:, j], k, mode="valid") for j in range(flat.shape[1])], axis=1)
    return out.reshape(x.shape)


def smooth_noise(rng: np.random.Generator, n: int, sigma: float, dims: int = 1) -> np.ndarray:
    """Smooth random signal (n, dims) with unit standard deviation (frame-correlated by sigma)."""
    pad = int(3 * sigma) + 1
    white = rng.standard_normal((n + 2 * pad, dims))
    sm = gaussian_smooth(white, sigma)[pad:pad + n]
    return sm / max(float(sm.std()), 1e-6)


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


def _normalize(v, eps=1e-12):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), eps)


def _frame_y_z(y_axis: np.ndarray, z_hint: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) with columns x, y, z: y given, z from a hint orthogonalized."""
    y = _normalize(y_axis)
    z = z_hint - (z_hint * y).sum(-1, keepdims=True) * y
    z = _normalize(z)
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
    s = np.sqrt(np.maximum(1.0 + np.stack((tr, m00 - m11 - m22, m11 - m00 - m22, m22 - m00 - m11), -1), 1e-12)) * 2.0
    # case 0: w largest
    c0 = np.stack((0.25 * s[..., 0], (m21 - m12) / s[..., 0], (m02 - m20) / s[..., 0], (m10 - m01) / s[..., 0]), -1)
    c1 = np.stack(((m21 - m12) / s[..., 1], 0.25 * s[..., 1], (m01 + m10) / s[..., 1], (m02 + m20) / s[..., 1]), -1)
    c2 = np.stack(((m02 - m20) / s[..., 2], (m01 + m10) / s[..., 2], 0.25 * s[..., 2], (m12 + m21) / s[..., 2]), -1)
    c3 = np.stack(((m10 - m01) / s[..., 3], (m02 + m20) / s[..., 3], (m12 + m21) / s[..., 3], 0.25 * s[..., 3]), -1)
    q = np.select([choice[..., None] == k for k in range(4)], [c0, c1, c2, c3])
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    return _normalize(q)


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
            arm_fwd=u(-0.02, 0.12), arm_abd=u(0.1, 0.22), elbow=u(0.12, 0.4), lean=u(-0.03, 0.1),
            pelvis_tilt=u(0.0, 0.1), head_pitch=u(-0.08, 0.15), step_width=u(-0.01, 0.035),
            toe_out=u(0.03, 0.2), stand_fwd=u(0.0, 0.04), knee_soft=u(0.0, 0.015), arm_swing=u(0.75, 1.3),
            shrug=u(-0.05, 0.1), noise=u(0.5, 1.5), cadence=u(0.92, 1.08),
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

    def copy(self) -> "Track":
        return Track(**{f.name: getattr(self, f.name).copy() for f in fields(self)})


_BLENDED = ("root", "heading", "pelvis", "spine", "neck", "arm", "hint", "shrug", "ankle", "foot_pitch", "foot_yaw")


def standing_track(n: int, state: State, style: Style) -> Track:
    """n frames of the neutral standing pose over the state's feet."""
    c = state.center(style)
    root = np.tile(np.array([c[0], style.height, c[2]]), (n, 1))
    arm = np.tile(np.array([style.arm_fwd, style.arm_abd, 0.0, style.elbow]), (n, 2, 1))
    hint = np.tile(_normalize(np.array([-0.15, 0.0, 1.0])), (n, 2, 1))
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
    tr.hint = _normalize(tr.hint)
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
    bad = np.abs((_normalize(hint) * d).sum(-1)) > 0.999
    if bad.any():
        upper[bad] = _frame_y_z(-d[bad], np.where(np.abs(d[bad, 2:3]) > 0.9, _UP, np.array([0.0, 0.0, 1.0])))
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
    p = _normalize(p)
    knee = hip + a * u + h * p
    return knee, hip + dc * u, p


def track_to_joints(tr: Track) -> np.ndarray:
    """Joint positions (n, 22, 3) of a track: local rotations, then forward kinematics."""
    return pose_to_joints(*track_to_pose(tr))


def pose_to_joints(quats: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Forward kinematics (true hierarchy) on the target skeleton: (..., 22, 4), (..., 3) -> (..., 22, 3).

    Frames are independent, so many clips can go through in one call (concatenated frames).
    """
    joints = forward_kinematics(torch.from_numpy(quats), torch.from_numpy(root), SKELETON, chains_from_root=False)
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
        mix = _normalize(pelvis_fwd + foot_fwd)
        reach_dir = _normalize(tr.ankle[:, side] - hips[:, side])
        raise_ = np.maximum((reach_dir * mix).sum(-1, keepdims=True), 0.0)
        pole = mix + 1.5 * raise_ * _UP
        knee, ankle, p = two_bone_ik(hips[:, side], tr.ankle[:, side], THIGH[side], SHIN[side], pole)
        thigh = _frame_y_z(hips[:, side] - knee, p)
        shin_y = _normalize(knee - ankle)
        shin_x = thigh[..., 0]
        G[:, knee_j] = thigh
        G[:, ankle_j] = np.stack((shin_x, shin_y, _cross(shin_x, shin_y)), axis=-1)
        pitch = tr.foot_pitch[:, side]
        f = np.cos(pitch)[:, None] * foot_fwd + np.sin(-pitch)[:, None] * _UP
        x = _normalize(_cross(_UP, f))
        G[:, toe_j] = np.stack((x, _cross(f, x), f), axis=-1)
    local = np.empty_like(G)
    local[:, 0] = G[:, 0]
    local[:, 1:] = np.swapaxes(G[:, _PARENT_INDEX], -1, -2) @ G[:, 1:]
    return matrix_to_quat(local), root


# ----------------------------------------------------------------------------- locomotion


@dataclass
class Gait:
    period: float  # stride period (s): one step of each foot
    duty: float  # fraction of the period a foot is on the ground (< 0.5: flight phases)
    lift: float  # swing height (m) per metre of step
    lift_base: float
    heel_strike: float  # toe-up angle at heel strike (rad) for a full forward step
    heel_off: float  # heel-up angle at toe off (rad)
    toe_strike: float  # heel-up angle at touchdown when stepping backwards
    toe_lift: float  # toe-up angle at lift-off when stepping backwards
    step_ref: float  # step length (m) for the full roll angles
    shift: float  # footholds lag the mid-stance pose by this fraction of the stance
    reach: float  # stance legs reach at most this fraction of their length
    swing_peak: float  # exponent placing the swing apex (< 1: earlier)
    td_frac: float = 0.15
    lo_frac: float = 0.45
    running: bool = False


def _interp_path(te, values, tq):
    """Linear interpolation of (m, k) samples at times tq, clamped at the ends."""
    tq = np.clip(tq, te[0], te[-1])
    return np.stack([np.interp(tq, te, values[:, j]) for j in range(values.shape[1])], axis=-1)


def _foot_ankle(flat, yaw, pitch, side):
    """Ankle position for a foot planted at `flat` (flat-foot ankle) rolled to `pitch`.

    Toe up (pitch < P0): the foot turns about the heel, taken at the ankle. Heel up (pitch > P0):
    it turns about the toe joint, which stays on its spot.
    """
    h = forward_dir(yaw)
    toe = flat + FOOT[side] * (math.cos(P0) * h - math.sin(P0) * _UP)
    rolled = toe - FOOT[side] * (np.cos(pitch)[..., None] * h - np.sin(pitch)[..., None] * _UP)
    return np.where((pitch > P0)[..., None], rolled, flat)


def plan_steps(te, pos, yaw, vbody, gait: Gait, style: Style, n: int, lead: int, first_center: float,
               start_feet: State | None):
    """Footsteps for a pelvis path sampled on the extended grid te (s).

    pos (m, 3) pelvis ground position, yaw (m,), vbody (m, 2) body-frame velocity (left, forward).
    The lead foot's first moving stance is centred on first_center; with start_feet (a standing
    start) every earlier stance stays on the start feet.
    Returns ankle (n, 2, 3), pitch (n, 2), foot yaw (n, 2), planted (n, 2), the final State's feet.
    """
    P, D = gait.period, gait.duty
    t = np.arange(n) / FPS
    ankle = np.zeros((n, 2, 3))
    pitch = np.full((n, 2), P0)
    fyaw = np.zeros((n, 2))
    planted = np.zeros((n, 2), dtype=bool)
    end_feet, end_yaw = np.zeros((2, 3)), np.zeros(2)
    for side in (0, 1):
        c0 = first_center + (0.0 if side == lead else P / 2)
        k0 = int(math.floor((te[0] - P - c0) / P))
        k1 = int(math.ceil((te[-1] + P - c0) / P))
        centers = c0 + P * np.arange(k0, k1 + 1)
        vb = _interp_path(te, vbody, centers)
        speed = np.linalg.norm(vb, axis=-1)
        fwd_sign = np.clip(vb[:, 1] / np.maximum(speed, 0.25), -1.0, 1.0)
        tq = centers - gait.shift * D * P * fwd_sign
        p = _interp_path(te, pos, tq)
        ya = np.interp(np.clip(tq, te[0], te[-1]), te, yaw)
        beta = np.maximum(np.abs(_interp_path(te, vbody, tq)[:, 0]) * P / 4 - 0.06, 0.0)
        lat = SIGN[side] * (style.half_width(side) + beta)
        flat = p + left_dir(ya) * lat[:, None] - forward_dir(ya) * style.stand_fwd
        flat[:, 1] = ANKLE_HEIGHT[side]
        fy = ya + SIGN[side] * style.toe_out
        if start_feet is not None:
            rest = centers < first_center - (P if side == lead else P / 2) + 1e-6
            flat[rest] = start_feet.feet[side]
            fy[rest] = start_feet.feet_yaw[side]
        # Merge footholds that do not move into one long stance.
        still = (np.linalg.norm(np.diff(flat, axis=0), axis=-1) < 0.015) & (np.abs(wrap_angle(np.diff(fy))) < 0.04)
        starts = np.concatenate([[0], np.flatnonzero(~still) + 1])
        groups = [list(range(a, b)) for a, b in zip(starts, np.concatenate([starts[1:], [len(centers)]]))]
        plants = []
        for gi, g in enumerate(groups):
            td = -np.inf if gi == 0 else centers[g[0]] - D * P / 2
            lo = np.inf if gi == len(groups) - 1 else centers[g[-1]] + D * P / 2
            plants.append([flat[g[0]].copy(), float(fy[g[0]]), td, lo])
        # Roll angles at touchdown and lift-off from the incoming and outgoing steps.
        rolls = []
        for k, (flat_k, yaw_k, _, _) in enumerate(plants):
            h = forward_dir(yaw_k)
            p_td = p_lo = P0
            if k > 0:
                f_in = float(np.clip((flat_k - plants[k - 1][0]) @ h / gait.step_ref, -1, 1))
                p_td = P0 - gait.heel_strike * f_in if f_in > 0 else P0 - gait.toe_strike * f_in
            if k < len(plants) - 1:
                f_out = float(np.clip((plants[k + 1][0] - flat_k) @ h / gait.step_ref, -1, 1))
                p_lo = P0 + gait.heel_off * f_out if f_out > 0 else P0 + gait.toe_lift * f_out
            rolls.append((p_td, p_lo))
        tau_td, tau_lo = gait.td_frac * D * P, gait.lo_frac * D * P
        for k, (flat_k, yaw_k, td, lo) in enumerate(plants):
            next_td = plants[k + 1][2] if k + 1 < len(plants) else np.inf
            if next_td < 0.0 or td > t[-1]:  # neither this stance nor the swing after it is in the clip
                continue
            m = (t >= td) & (t <= lo)
            if m.any():
                tt = t[m]
                p_td, p_lo = rolls[k]
                pp = np.full(tt.shape, P0)
                if np.isfinite(td):
                    pp += (p_td - P0) * (1 - smoothstep((tt - td) / tau_td))
                if np.isfinite(lo):
                    pp += (p_lo - P0) * smoothstep((tt - (lo - tau_lo)) / tau_lo)
                ankle[m, side] = _foot_ankle(flat_k, yaw_k, pp, side)
                pitch[m, side] = pp
                fyaw[m, side] = yaw_k
                planted[m, side] = True
            if k == len(plants) - 1:
                break
            nxt = plants[k + 1]
            m = (t > lo) & (t < nxt[2])
            if not m.any():
                continue
            tt = t[m]
            u = (tt - lo) / (nxt[2] - lo)
            p_a, p_b = rolls[k][1], rolls[k + 1][0]
            a0 = _foot_ankle(flat_k, yaw_k, np.array(p_a), side)
            a1 = _foot_ankle(nxt[0], nxt[1], np.array(p_b), side)
            mh = smoothstep(u ** (1.35 if gait.running else 1.0))
            mv = smoothstep(u)
            step = float(np.linalg.norm((nxt[0] - flat_k)[[0, 2]]))
            lift = gait.lift_base + gait.lift * step
            bump = np.sin(np.pi * u ** gait.swing_peak) ** 1.5
            pos_s = a0 + (a1 - a0) * mh[:, None]
            pos_s[:, 1] = a0[1] + (a1[1] - a0[1]) * mv + lift * bump
            pp = p_a + (p_b - p_a) * mv
            toe_y = pos_s[:, 1] - FOOT[side] * np.sin(pp)
            pos_s[:, 1] += np.maximum(0.012 * np.sin(np.pi * u) - toe_y, 0.0)
            ankle[m, side] = pos_s
            pitch[m, side] = pp
            fyaw[m, side] = yaw_k + wrap_angle(nxt[1] - yaw_k) * mv
        end_feet[side], end_yaw[side] = plants[-1][0], plants[-1][1]
        # A final plant that starts after the clip end leaves the last swing target as the end.
    return ankle, pitch, fyaw, planted, State(0.0, end_feet, end_yaw)


def _speed_profile(te, t_a, t_b, ramp_in, ramp_out, moving_start, moving_end):
    """Fraction (m,) of the cruise speed: 0 standing, eased ramps, 1 cruising."""
    s = np.ones_like(te)
    if not moving_start:
        s = s * smoothstep((te - t_a) / ramp_in)
    if not moving_end:
        s = s * smoothstep((t_b - te) / ramp_out)
    return s


def _integrate(te, vel, anchor_index, anchor):
    """Positions (m, 3) from velocities (m, 3) by the trapezoid rule, pinned at one sample."""
    dt = np.diff(te)[:, None]
    steps = 0.5 * (vel[1:] + vel[:-1]) * dt
    pos = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)], axis=0)
    return pos - pos[anchor_index] + anchor


def locomotion(rng, n, state: State, style: Style, *, gait: Gait, te, yaw, vbody, t_start, lead,
               height, start_standing: bool, sway=0.35, twist=0.25, arm_gain=1.0, elbow=None,
               lean=0.0, arm_abd=None, bounce=0.0):
    """Animate the legs, pelvis and arms for a pelvis path given on the extended grid te.

    yaw (m,), vbody (m, 2) body-frame velocity (left, forward); the path starts at the state's
    neutral centre at t = 0. height: nominal pelvis height, (n,) or scalar; bounce: amplitude of
    a pelvis oscillation lowest at each mid-stance (running), scaled by the speed.
    """
    E = int(round(-te[0] * FPS))
    vel = vbody[:, :1] * left_dir(yaw) + vbody[:, 1:] * forward_dir(yaw)
    pos = _integrate(te, vel, E, state.center(style))
    gait = replace(gait, period=gait.period * style.cadence)
    # The lead foot lifts off at t_start (standing starts).
    first_center = t_start + gait.period * (1 - gait.duty / 2) + 0.02
    ankle, pitch, fyaw, planted, end = plan_steps(
        te, pos, yaw, vbody, gait, style, n, lead, first_center, state if start_standing else None)
    tr = standing_track(n, state, style)
    tr.heading = yaw[E:E + n].copy()
    root = pos[E:E + n].copy()
    tr.ankle, tr.foot_pitch, tr.foot_yaw, tr.planted = ankle, pitch, fyaw, planted
    fwd, left = forward_dir(tr.heading), left_dir(tr.heading)
    vb = vbody[E:E + n]
    # Lateral sway of the pelvis over the supporting foot (not along the direction of travel).
    w = gaussian_smooth(planted.astype(np.float64), 1.5) + 1e-3
    support = (w[:, :, None] * ankle).sum(1) / w.sum(1, keepdims=True)
    lateral_travel = np.abs(vb[:, 0]) > np.abs(vb[:, 1]) + 0.05
    dev = ((support - root) * left).sum(-1)
    dev = np.where(lateral_travel, 0.0, dev)
    root += gaussian_smooth(sway * dev, 2.0)[:, None] * left
    # Pelvis and thorax counter-rotation with the legs, pelvis list with the swing leg.
    f_rel = ((ankle - root[:, None]) * fwd[:, None]).sum(-1)
    lift = ankle[:, :, 1] - ANKLE_HEIGHT
    delta = gaussian_smooth(f_rel[:, 0] - f_rel[:, 1], 1.0)
    speed = np.linalg.norm(vb, axis=-1)
    tr.pelvis[:, 2] = -twist * delta
    tr.pelvis[:, 1] = -0.35 * gaussian_smooth(lift[:, 0] - lift[:, 1], 1.0)
    tr.pelvis[:, 0] = style.pelvis_tilt + 0.02 * np.minimum(speed, 3.0) + (0.03 if gait.running else 0.0)
    tr.spine[:, 0] = style.lean + lean
    tr.spine[:, 2] = 1.7 * twist * delta
    tr.neck[:, 1] = -0.9 * (tr.pelvis[:, 2] + tr.spine[:, 2])
    # Arms swing opposite to the legs.
    g = arm_gain * style.arm_swing
    tr.arm[:, 0, 0] = style.arm_fwd - g * delta / 2
    tr.arm[:, 1, 0] = style.arm_fwd + g * delta / 2
    if arm_abd is not None:
        tr.arm[:, :, 1] = arm_abd
    if elbow is None:
        tr.arm[:, :, 3] = style.elbow + 0.4 * np.maximum(tr.arm[:, :, 0] - style.arm_fwd, 0.0)
    else:
        tr.arm[:, :, 3] = elbow + 0.25 * (tr.arm[:, :, 0] - style.arm_fwd)
        tr.hint[:] = _normalize(np.array([-0.3, 0.0, 1.0]))
    # Pelvis height: nominal, never above what the stance legs reach; ballistic over flights.
    tr.root = root
    h_nom = np.broadcast_to(np.asarray(height, dtype=np.float64), (n,)).copy()
    if bounce:
        t = np.arange(n) / FPS
        frac = np.clip(speed / max(float(speed.max()), 1e-6), 0.0, 1.0)
        h_nom -= bounce * frac * np.cos(4 * np.pi * (t - first_center) / gait.period)
    cap = reach_cap(tr, gait.reach, root)
    h = np.minimum(h_nom, cap)
    air = ~planted.any(axis=1)
    if air.any():
        i = 0
        while i < n:
            if not air[i]:
                i += 1
                continue
            j = i
            while j < n and air[j]:
                j += 1
            y0 = h[i - 1] if i > 0 else h[j] if j < n else h_nom[i]
            y1 = h[j] if j < n else y0
            dur = (j - i + 1) / FPS
            u = np.arange(1, j - i + 1) / (j - i + 1)
            h[i:j] = y0 + (y1 - y0) * u + GRAVITY * dur * dur / 2 * u * (1 - u)
            i = j
    h = gaussian_smooth(h, 1.2)
    root[:, 1] = np.minimum(h, reach_cap(tr, min(gait.reach + 0.004, 0.999), root))
    tr.root = root
    end.heading = float(yaw[E + n - 1])
    return tr, end


def _extended_grid(n: int, margin_s: float = 2.0):
    E = int(margin_s * FPS)
    return np.arange(-E, n + E) / FPS


def walk_gait(direction: str, v: float) -> Gait:
    if direction == "forward":
        return Gait(period=2 / (1.2 + 0.7 * v), duty=max(0.52, 0.64 - 0.055 * v), lift=0.035, lift_base=0.04,
                    heel_strike=0.45, heel_off=0.7, toe_strike=0.55, toe_lift=0.35, step_ref=1.1,
                    shift=0.15, reach=0.995, swing_peak=0.85)
    if direction == "backward":
        return Gait(period=2 / (1.4 + 0.7 * v), duty=max(0.5, 0.62 - 0.06 * v), lift=0.04, lift_base=0.05,
                    heel_strike=0.45, heel_off=0.6, toe_strike=0.6, toe_lift=0.4, step_ref=1.0,
                    shift=0.15, reach=0.995, swing_peak=1.0)
    return Gait(period=2 / (1.6 + 1.3 * v), duty=max(0.34, 0.62 - 0.14 * v), lift=0.03, lift_base=0.05,
                heel_strike=0.2, heel_off=0.3, toe_strike=0.3, toe_lift=0.2, step_ref=1.0,
                shift=0.0, reach=0.993, swing_peak=1.0)


def run_gait(v: float) -> Gait:
    return Gait(period=2 / (2.6 + 0.25 * v), duty=0.42 - 0.025 * v, lift=0.1, lift_base=0.15,
                heel_strike=0.1, heel_off=0.8, toe_strike=0.5, toe_lift=0.3, step_ref=1.6,
                shift=0.1, reach=0.975, swing_peak=0.7, td_frac=0.3, lo_frac=0.55, running=True)


# ----------------------------------------------------------------------------- actions


@dataclass
class Context:
    moving_start: bool = False  # the part may begin in motion (first part of a clip)
    moving_end: bool = False  # the part may end in motion (last part of a clip)
    last: bool = False  # nothing follows this part


def act_stand(rng, n, state, style, params, ctx):
    tr = standing_track(n, state, style)
    t = np.arange(n) / FPS
    left, fwd = left_dir(state.heading), forward_dir(state.heading)
    # Weight shifts between the feet and a slow sway.
    shift = rng.uniform(-0.035, 0.035) * smoothstep((t - rng.uniform(0, 1.5)) / rng.uniform(0.6, 1.5))
    sway = 0.008 * smooth_noise(rng, n, 12.0, 2)
    tr.root += (shift + sway[:, 0])[:, None] * left + sway[:, 1:] * fwd
    tr.pelvis[:, 1] += -3.0 * shift * 0.3
    tr.root[:, 1] -= 0.01 * np.abs(smooth_noise(rng, n, 15.0)[:, 0])
    tr.neck[:, 1] += rng.uniform(0.0, 0.35) * smooth_noise(rng, n, 15.0)[:, 0]
    if rng.random() < 0.3:  # hands on the hips (kept there when nothing follows)
        t0 = rng.uniform(0.1, 0.6)
        if ctx.last and rng.random() < 0.5:
            k = keyframes(t, [0, t0, t0 + 0.6], [0, 0, 1])
        else:
            t1 = max(t0 + 0.7, t[-1] - rng.uniform(0.7, 1.0))
            k = keyframes(t, [0, t0, t0 + 0.6, t1, t1 + 0.6], [0, 0, 1, 1, 0])
        _blend_arms(tr, k, np.array([0.0, 0.75, 0.0, 1.5]), np.array([-1.0, 0.1, 0.15]), (0, 1))
    return tr, state


def _blend_arms(tr: Track, k, pose, hint, sides):
    """Blend the arms of `sides` towards pose (4,) and hint (3,) by weight k (n,)."""
    k = np.asarray(k, dtype=np.float64)[:, None]
    for s in sides:
        tr.arm[:, s] = tr.arm[:, s] * (1 - k) + pose * k
        tr.hint[:, s] = _normalize(tr.hint[:, s] * (1 - k) + _normalize(np.asarray(hint, dtype=np.float64)) * k)


def _timeline_fit(rng, n, parts, pads=(0.1, 0.2), fill: int | None = None):
    """Phase durations (s) drawn in their (min, max) ranges that fit n frames, and the lead pad.

    The time left over is idle standing split between the lead and the tail pads, or, with
    `fill`, goes to that phase (e.g. the waving itself) beyond short pads.
    """
    T = (n - 1) / FPS
    mins = np.array([p[0] for p in parts])
    maxs = np.array([p[1] for p in parts])
    if mins.sum() + 2 * pads[0] > T + 1e-9:
        raise Infeasible(f"needs {mins.sum() + 2 * pads[0]:.2f} s, has {T:.2f} s")
    d = rng.uniform(mins, maxs)
    budget = T - 2 * pads[0]
    if d.sum() > budget:
        excess = d.sum() - budget
        room = d - mins
        d = d - room * (excess / room.sum())
    spare = T - d.sum()
    if fill is not None:
        lead, tail = rng.uniform(pads[0], pads[1], 2)
        scale = min(1.0, spare / (lead + tail))
        lead, tail = lead * scale, tail * scale
        d[fill] += spare - lead - tail
        return d, lead
    lead = pads[0] + rng.uniform(0.0, 1.0) * min(spare - 2 * pads[0], pads[1] + 0.4 * (spare - 2 * pads[0]))
    return d, max(lead, pads[0])


def _walk_path(rng, n, style, v_mean, ctx, extra_pad=(0.05, 0.35), ramp=(0.45, 0.8), vmax=2.3):
    """Speed profile on the extended grid for a walk/run of mean speed v_mean over n frames."""
    te = _extended_grid(n)
    T = (n - 1) / FPS
    moving_start = ctx.moving_start and rng.random() < 0.45
    moving_end = ctx.moving_end and rng.random() < 0.45
    for attempt in range(4):
        t_a = 0.0 if moving_start else rng.uniform(*extra_pad) * (1 - 0.3 * attempt)
        t_b = T if moving_end else T - rng.uniform(*extra_pad) * (1 - 0.3 * attempt)
        r_in = rng.uniform(*ramp) * (1 - 0.15 * attempt)
        r_out = rng.uniform(*ramp) * (1 - 0.15 * attempt)
        eff = (t_b - t_a) - (0.0 if moving_start else r_in / 2) - (0.0 if moving_end else r_out / 2)
        v = v_mean * T / max(eff, 1e-6)
        if v <= vmax:
            s = _speed_profile(te, t_a, t_b, r_in, r_out, moving_start, moving_end)
            return te, s, v, t_a, not moving_start
    raise Infeasible(f"mean speed {v_mean:.2f} m/s over {T:.2f} s needs {v:.2f} m/s")


def act_walk(rng, n, state, style, params, ctx):
    direction, speed = params["direction"], params["speed"]
    lo, hi = WALK_SPEEDS[speed]
    v_mean = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo))
    te, s, v, t_a, standing = _walk_path(rng, n, style, v_mean, ctx)
    gait = walk_gait(direction, v)
    body = {"forward": (0.0, 1.0), "backward": (0.0, -1.0), "left": (1.0, 0.0), "right": (-1.0, 0.0)}[direction]
    vbody = v * s[:, None] * np.array(body)
    drift = rng.uniform(-0.12, 0.12) * smoothstep((te - t_a) / max(te[-1] - t_a, 1e-6))
    yaw = state.heading + drift
    lead = {"left": 0, "right": 1}.get(direction, int(rng.integers(2)))
    lateral = direction in ("left", "right")
    h = style.height + 0.01
    tr, end = locomotion(rng, n, state, style, gait=gait, te=te, yaw=yaw, vbody=vbody, t_start=t_a, lead=lead,
                         height=h, start_standing=standing, arm_gain=0.0 if lateral else 1.1,
                         lean=0.04 if direction == "backward" else 0.0,
                         arm_abd=style.arm_abd + (0.1 if lateral else 0.0))
    return tr, end


def act_run(rng, n, state, style, params, ctx):
    v_mean = rng.uniform(2.45, 3.3)
    te, s, v, t_a, standing = _walk_path(rng, n, style, v_mean, ctx, extra_pad=(0.05, 0.25), ramp=(0.55, 0.85), vmax=3.5)
    v = max(v, 2.5)
    gait = run_gait(v)
    vbody = v * s[:, None] * np.array([0.0, 1.0])
    yaw = state.heading + rng.uniform(-0.1, 0.1) * smoothstep((te - t_a) / max(te[-1] - t_a, 1e-6))
    E = int(round(-te[0] * FPS))
    k = s[E:E + n]
    h = style.height * (1 - k) + (style.height - 0.05 - 0.015 * (v - 2.5)) * k
    tr, end = locomotion(rng, n, state, style, gait=gait, te=te, yaw=yaw, vbody=vbody, t_start=t_a,
                         lead=int(rng.integers(2)), height=h, start_standing=standing, sway=0.2, twist=0.2,
                         arm_gain=1.5, elbow=rng.uniform(1.35, 1.65), lean=rng.uniform(0.02, 0.1),
                         arm_abd=style.arm_abd + 0.05, bounce=0.045)
    # Elbows flex fully only once running: ease them in and out with the speed.
    rest = np.array([style.elbow, style.elbow])
    tr.arm[:, :, 3] = rest * (1 - k[:, None]) + tr.arm[:, :, 3] * k[:, None]
    return tr, end


def act_turn(rng, n, state, style, params, ctx):
    sign = 1.0 if params["side"] == "left" else -1.0
    angle = math.radians(float(params["angle"])) * rng.uniform(0.95, 1.05)
    T = (n - 1) / FPS
    dur = rng.uniform(1.0, 1.6) if params["angle"] == 90 else rng.uniform(1.6, 2.5)
    dur = min(dur, T - 0.5)
    if dur < 0.8:
        raise Infeasible("turn too short")
    t_a = rng.uniform(0.1, max(0.15, min(0.6, T - dur - 0.35)))
    te = _extended_grid(n)
    yaw = state.heading + sign * angle * smoothstep((te - t_a) / dur)
    gait = Gait(period=rng.uniform(0.8, 1.0), duty=0.62, lift=0.1, lift_base=0.05, heel_strike=0.1, heel_off=0.3,
                toe_strike=0.2, toe_lift=0.1, step_ref=0.6, shift=0.0, reach=0.995, swing_peak=0.9)
    vbody = np.zeros((len(te), 2))
    tr, end = locomotion(rng, n, state, style, gait=gait, te=te, yaw=yaw, vbody=vbody, t_start=t_a - 0.15 * gait.period,
                         lead=0 if sign > 0 else 1, height=style.height, start_standing=True, sway=0.3,
                         twist=0.15, arm_gain=0.3)
    # The head leads into the turn.
    E = int(round(-te[0] * FPS))
    lead_ang = np.interp(np.arange(n) / FPS + 0.3, te, yaw) - yaw[E:E + n]
    tr.neck[:, 1] += 0.6 * lead_ang
    tr.spine[:, 2] += 0.3 * lead_ang
    return tr, end


def act_circle(rng, n, state, style, params, ctx):
    sign = 1.0 if params["side"] == "counterclockwise" else -1.0
    T = (n - 1) / FPS
    theta = math.radians(rng.uniform(352.0, 372.0))
    te = _extended_grid(n)
    for _ in range(8):
        t_a = rng.uniform(0.05, 0.3)
        t_b = T - rng.uniform(0.05, 0.3)
        r_in, r_out = rng.uniform(0.5, 0.8), rng.uniform(0.5, 0.8)
        eff = (t_b - t_a) - (r_in + r_out) / 2
        radius = rng.uniform(1.0, 1.6)
        v = radius * theta / eff
        if v > 1.75:
            radius = 1.75 * eff / theta
        elif v < 0.9:
            radius = 0.9 * eff / theta
        v = radius * theta / eff
        if 1.0 <= radius <= 2.0 and 0.85 <= v <= 1.8:
            break
    else:
        raise Infeasible("no circle fits")
    s = _speed_profile(te, t_a, t_b, r_in, r_out, False, False)
    dt = np.diff(te, prepend=te[0])
    yaw = state.heading + sign * np.cumsum(v * s * dt) / radius
    yaw = yaw - (yaw[int(round(-te[0] * FPS))] - state.heading)
    vbody = v * s[:, None] * np.array([0.0, 1.0])
    gait = walk_gait("forward", v)
    gait = replace(gait, period=gait.period * 0.8)  # shorter, quicker steps on a tight circle
    tr, end = locomotion(rng, n, state, style, gait=gait, te=te, yaw=yaw, vbody=vbody, t_start=t_a,
                         lead=0 if sign < 0 else 1, height=style.height + 0.01, start_standing=True,
                         arm_gain=1.0)
    E = int(round(-te[0] * FPS))
    lean = sign * 0.06 * s[E:E + n] * v / 1.5  # lean into the curve
    tr.pelvis[:, 1] += lean * 0.5
    tr.neck[:, 1] += sign * 0.15 * s[E:E + n]
    return tr, end


def act_jump(rng, n, state, style, params, ctx):
    count = int(params["count"])
    forward = params["mode"] == "forward"
    H = style.height
    phases = []
    for j in range(count):
        phases += [(0.3, 0.45), (0.12, 0.18), (0.37, 0.46), (0.18, 0.28)]  # crouch, push, flight, land
        if j < count - 1:
            phases += [(0.0, 0.5)]  # pause standing between jumps (0: rebound)
    phases += [(0.35, 0.6)]  # recover
    d, lead = _timeline_fit(rng, n, phases)
    t = np.arange(n) / FPS
    tr = standing_track(n, state, style)
    fwd_dir = forward_dir(state.heading)
    if forward:
        dists = rng.uniform(0.5, 0.85, count)
        dirs = [fwd_dir] * count
    else:
        dists = rng.uniform(0.0, 0.05, count)
        dirs = [forward_dir(state.heading + rng.uniform(-np.pi, np.pi))] * count
    travel = fwd_dir if forward else dirs[0]
    y_knots, x_knots = [(0.0, H, 0.0), (lead, H, 0.0)], [(0.0, 0.0, 0.0), (lead, 0.0, 0.0)]
    hb_keys = [(0.0, 0.0), (lead, 0.0)]  # hips back along the facing (crouch and landing)
    arm_keys = [(0.0, 0.0), (lead, 0.0)]
    spine_keys = [(0.0, 0.0), (lead, 0.0)]
    flights, takeoff = [], []
    tcur, x0, i = lead, 0.0, 0
    a = 0.15 if forward else 0.3
    for j in range(count):
        crouch, push, flight, land = d[i:i + 4]
        i += 4
        depth, absorb = rng.uniform(0.08, 0.19), rng.uniform(0.07, 0.17)
        y_to = H + rng.uniform(0.03, 0.055)
        v0 = GRAVITY * flight / 2
        t_cb, t_to = tcur + crouch, tcur + crouch + push
        t_ld, t_ab = t_to + flight, t_to + flight + land
        J = dists[j]
        vh = (1 - 2 * a) * J / flight
        y_knots += [(t_cb, H - depth, 0.0), (t_to, y_to, v0), (t_ld, y_to, -v0), (t_ab, H - absorb, 0.0)]
        x_knots += [(t_cb, x0, 0.0), (t_to, x0 + a * J, vh), (t_ld, x0 + (1 - a) * J, vh), (t_ab, x0 + J, 0.0)]
        b = rng.uniform(0.03, 0.08)
        hb_keys += [(t_cb, b), (t_to, 0.4 * b), (t_to + 0.5 * flight, 0.0), (t_ld, 0.0), (t_ab, rng.uniform(0.02, 0.06))]
        flights.append((t_to, t_ld, y_to))
        takeoff.append((t_cb, t_to, t_ld, t_ab))
        arm_keys += [(t_cb, -rng.uniform(0.5, 0.9)), (t_to + 0.3 * flight, rng.uniform(1.6, 2.6)), (t_ab, rng.uniform(0.2, 0.5))]
        spine_keys += [(t_cb, rng.uniform(0.25, 0.45)), (t_to, rng.uniform(0.0, 0.1)), (t_ab, rng.uniform(0.15, 0.3))]
        x0 += J
        tcur = t_ab
        if j < count - 1:
            pause = d[i]
            i += 1
            if pause > 0.15:
                tcur += pause
                y_knots.append((tcur, H, 0.0))
                x_knots.append((tcur, x0, 0.0))
                for keys in (hb_keys, arm_keys, spine_keys):
                    keys.append((tcur, 0.0))
    tcur += d[i]
    y_knots.append((tcur, H, 0.0))
    x_knots.append((tcur, x0, 0.0))
    for keys in (hb_keys, arm_keys, spine_keys):
        keys += [(tcur, 0.0), (t[-1] + 1.0, 0.0)]
    y = hermite(t, *zip(*y_knots))
    if y.min() < H - 0.21:  # keep landings shallower than a squat
        raise Infeasible("landing too deep")
    for t0, t1, y_to in flights:  # exact ballistic arcs
        m = (t >= t0) & (t <= t1)
        tau = t[m] - t0
        y[m] = y_to + GRAVITY * (t1 - t0) / 2 * tau - GRAVITY * tau * tau / 2
    xs = hermite(t, *zip(*x_knots))
    hb = keyframes(t, *zip(*hb_keys))
    tr.root = state.center(style) + xs[:, None] * travel - hb[:, None] * fwd_dir
    tr.root[:, 1] = y
    # Feet: planted before take-off (heels rise on the push), fly with the body, land on the toes.
    feet = state.feet.copy()
    fy = state.feet_yaw.copy()
    p_to = P0 + rng.uniform(0.7, 0.85)
    p_land = P0 + rng.uniform(0.4, 0.6)
    tuck = rng.uniform(0.04, 0.12)
    for j, (t_cb, t_to, t_ld, t_ab) in enumerate(takeoff):
        new_feet = feet + dists[j] * travel
        new_feet[:, 1] = ANKLE_HEIGHT
        for s in (0, 1):
            # push: heel rises about the toe
            m = (t >= t_cb) & (t < t_to)
            pp = P0 + (p_to - P0) * smoothstep((t[m] - t_cb) / (t_to - t_cb))
            tr.ankle[m, s] = _foot_ankle(feet[s], fy[s], pp, s)
            tr.foot_pitch[m, s] = pp
            # flight: toe path from the old to the new toe spot, lifted with the pelvis
            m = (t >= t_to) & (t < t_ld)
            u = (t[m] - t_to) / (t_ld - t_to)
            h = forward_dir(fy[s])
            toe0 = feet[s] + FOOT[s] * (math.cos(P0) * h - math.sin(P0) * _UP)
            toe1 = new_feet[s] + FOOT[s] * (math.cos(P0) * h - math.sin(P0) * _UP)
            toe = toe0 + (toe1 - toe0) * smoothstep(u)[:, None]
            toe[:, 1] = 0.85 * (y[m] - (y[m][0] if m.any() else 0.0)) + tuck * np.sin(np.pi * u)
            pp = p_to + (p_land - p_to) * smoothstep(u)
            tr.ankle[m, s] = toe - FOOT[s] * (np.cos(pp)[:, None] * h - np.sin(pp)[:, None] * _UP)
            tr.foot_pitch[m, s] = pp
            tr.planted[m, s] = False
            # landing: heel lowers about the toe
            m = t >= t_ld
            pp = p_land + (P0 - p_land) * smoothstep((t[m] - t_ld) / max(t_ab - t_ld, 0.05))
            tr.ankle[m, s] = _foot_ankle(new_feet[s], fy[s], pp, s)
            tr.foot_pitch[m, s] = pp
        feet = new_feet
    e = keyframes(t, *zip(*arm_keys))
    tr.arm[:, :, 0] = style.arm_fwd + e[:, None]
    tr.arm[:, :, 3] = style.elbow + 0.3 * np.abs(e)[:, None] * 0.3
    tr.arm[:, :, 1] = style.arm_abd + 0.1 * np.clip(e, 0, None)[:, None]
    tr.spine[:, 0] = style.lean + keyframes(t, *zip(*spine_keys))
    tr.pelvis[:, 0] = style.pelvis_tilt + 0.5 * (tr.spine[:, 0] - style.lean)
    tr.neck[:, 0] = style.head_pitch - 0.5 * (tr.spine[:, 0] - style.lean)
    end = State(state.heading, feet, fy)
    return tr, end


def act_squat(rng, n, state, style, params, ctx):
    count = int(params["count"])
    phases = []
    for j in range(count):
        phases += [(0.55, 1.0), (0.0, 0.45), (0.55, 0.95)]  # down, hold, up
        if j < count - 1:
            phases += [(0.05, 0.4)]
    d, lead = _timeline_fit(rng, n, phases)
    t = np.arange(n) / FPS
    tr = standing_track(n, state, style)
    H = style.height
    keys_t, keys_v = [0.0, lead], [0.0, 0.0]
    tc, i = lead, 0
    for j in range(count):
        down, hold, up = d[i:i + 3]
        i += 3
        depth = rng.uniform(0.31, 0.42)
        keys_t += [tc + down, tc + down + hold, tc + down + hold + up]
        keys_v += [depth, depth, 0.0]
        tc += down + hold + up
        if j < count - 1:
            tc += d[i]
            keys_t.append(tc)
            keys_v.append(0.0)
            i += 1
    keys_t.append(t[-1] + 1.0)
    keys_v.append(0.0)
    dip = keyframes(t, keys_t, keys_v)
    fwd = forward_dir(state.heading)
    back = rng.uniform(0.4, 0.65)
    tr.root[:, 1] = H - dip
    tr.root -= (back * dip)[:, None] * fwd
    tr.spine[:, 0] += dip * rng.uniform(0.3, 0.6)
    tr.pelvis[:, 0] += dip * rng.uniform(1.0, 1.5)
    tr.neck[:, 0] -= dip * 1.5
    k = dip / 0.4
    variant = rng.integers(3)
    if variant == 0:  # arms forwards for balance
        pose = np.array([rng.uniform(1.2, 1.55), 0.05, 0.1, 0.15])
        _blend_arms(tr, k, pose, np.array([0.0, 1.0, 0.0]), (0, 1))
    elif variant == 1:  # hands on the hips
        m = smoothstep(t / 0.5) * smoothstep((t[-1] - t) / 0.5)
        _blend_arms(tr, m, np.array([0.0, 0.75, 0.0, 1.5]), np.array([-1.0, 0.1, 0.15]), (0, 1))
    else:  # hands clasped in front of the chest
        m = smoothstep((t - lead + 0.3) / 0.5) * smoothstep((t[-1] - t - 0.1) / 0.5)
        _blend_arms(tr, m, np.array([0.75, 0.3, 0.0, 1.55]), np.array([-1.0, 0.3, 0.4]), (0, 1))
    return tr, state


def act_wave(rng, n, state, style, params, ctx):
    hand = params["hand"]
    sides = (0, 1) if hand == "both" else ((0,) if hand == "left" else (1,))
    d, lead = _timeline_fit(rng, n, [(0.3, 0.55), (1.0, 1.5), (0.3, 0.55)], pads=(0.05, 0.5), fill=1)
    t = np.arange(n) / FPS
    t1, t2, t3 = lead + d[0], lead + d[0] + d[1], lead + d.sum()
    k = keyframes(t, [0, lead, t1, t2, t3, t[-1] + 1], [0, 0, 1, 1, 0, 0])
    tr = standing_track(n, state, style)
    freq = rng.uniform(1.6, 2.8)
    amp = rng.uniform(0.3, 0.45)
    phase = rng.uniform(0, 2 * np.pi)
    anti = rng.random() < 0.5
    for s in sides:
        abd = rng.uniform(1.75, 2.6)
        e = rng.uniform(0.0, 0.35)
        bend = rng.uniform(0.55, 0.95)
        ph = phase + (np.pi if (anti and s == 1) else 0.0)
        osc = np.sin(2 * np.pi * freq * t + ph) * smoothstep((t - t1 + 0.2) / 0.3)
        pose = np.stack([np.full(n, e), np.full(n, abd), np.zeros(n), bend + amp * osc], axis=-1)
        hint = np.stack([-np.sin(0.3 * osc), np.cos(0.3 * osc), np.full(n, 0.15)], axis=-1)
        kk = k[:, None]
        tr.arm[:, s] = tr.arm[:, s] * (1 - kk) + pose * kk
        tr.hint[:, s] = _normalize(tr.hint[:, s] * (1 - kk) + hint * kk)
        tr.shrug[:, s] += 0.15 * k
    if len(sides) == 1:
        s = sides[0]
        tr.spine[:, 1] += -SIGN[s] * 0.05 * k  # lean away from the raised arm
        tr.neck[:, 1] += SIGN[s] * rng.uniform(0.0, 0.25) * k
    return tr, state


def act_raise_arms(rng, n, state, style, params, ctx):
    T = (n - 1) / FPS
    reps = 2 if T > 4.2 and rng.random() < 0.4 else 1
    phases = []
    for j in range(reps):
        phases += [(0.45, 0.9), (0.5, 1.0), (0.45, 0.9)]
        if j < reps - 1:
            phases += [(0.1, 0.5)]
    d, lead = _timeline_fit(rng, n, phases, pads=(0.05, 0.6), fill=1)
    t = np.arange(n) / FPS
    keys_t, keys_v = [0.0, lead], [0.0, 0.0]
    tc, i = lead, 0
    for j in range(reps):
        up, hold, down = d[i:i + 3]
        i += 3
        keys_t += [tc + up, tc + up + hold, tc + up + hold + down]
        keys_v += [1.0, 1.0, 0.0]
        tc += up + hold + down
        if j < reps - 1:
            tc += d[i]
            i += 1
            keys_t.append(tc)
            keys_v.append(0.0)
    keys_t.append(t[-1] + 1.0)
    keys_v.append(0.0)
    k = keyframes(t, keys_t, keys_v)
    tr = standing_track(n, state, style)
    sideways = rng.random() < 0.5
    top = rng.uniform(2.65, 2.95)
    for s in (0, 1):
        if sideways:
            pose = np.array([0.05, top, 0.0, rng.uniform(0.05, 0.3)])
            hint = np.array([-1.0, 0.3, 0.2])
        else:
            pose = np.array([top, 0.15, 0.0, rng.uniform(0.05, 0.3)])
            hint = np.array([0.0, 0.2, -1.0])
        # Raise through the intermediate elevations rather than blending the end poses.
        tr.arm[:, s] = tr.arm[:, s] * (1 - k[:, None]) + pose * k[:, None]
        tr.hint[:, s] = _normalize(tr.hint[:, s] * (1 - k[:, None]) + _normalize(hint) * k[:, None])
        tr.shrug[:, s] += 0.25 * k
    tr.neck[:, 0] -= 0.2 * k
    return tr, state


def act_kick(rng, n, state, style, params, ctx):
    side = 0 if params["foot"] == "left" else 1
    T = (n - 1) / FPS
    kicks = 2 if T > 3.3 and rng.random() < 0.35 else 1
    phases = [(0.3, 0.5)]  # shift weight
    for _ in range(kicks):
        phases += [(0.22, 0.35), (0.12, 0.2), (0.0, 0.15), (0.18, 0.3)]  # chamber, extend, hold, retract
    phases += [(0.25, 0.4), (0.25, 0.45)]  # put down, shift back
    d, lead = _timeline_fit(rng, n, phases)
    t = np.arange(n) / FPS
    tr = standing_track(n, state, style)
    fwd, left = forward_dir(state.heading), left_dir(state.heading)
    shift = rng.uniform(0.05, 0.08)
    t_shift = lead + d[0]
    t_up = t_shift  # leg leaves the ground
    i = 1
    keys_t, keys_f, keys_h, keys_p = [t_up], [0.0], [0.0], [P0]
    tc = t_up
    height = rng.uniform(0.5, 0.75)
    reach = rng.uniform(0.5, 0.68)
    for _ in range(kicks):
        ch, ex, ho, re = d[i:i + 4]
        i += 4
        ch_f, ch_h = rng.uniform(0.1, 0.25), rng.uniform(0.3, 0.42)
        keys_t += [tc + ch, tc + ch + ex, tc + ch + ex + ho, tc + ch + ex + ho + re]
        keys_f += [ch_f, reach, reach, ch_f]
        keys_h += [ch_h, height, height, ch_h]
        keys_p += [0.9, rng.uniform(-0.5, 0.0), rng.uniform(-0.5, 0.0), 0.9]
        tc += ch + ex + ho + re
    down, back = d[i], d[i + 1]
    t_down = tc + down
    keys_t += [t_down, t[-1] + 1.0]
    keys_f += [0.0, 0.0]
    keys_h += [0.0, 0.0]
    keys_p += [P0, P0]
    f = keyframes(t, keys_t, keys_f)
    hgt = keyframes(t, keys_t, keys_h)
    pitch = keyframes(t, keys_t, keys_p)
    air = (t > t_up) & (t < t_down)
    # Pelvis over the support foot, leaning back while kicking.
    w = keyframes(t, [0, lead, t_shift, t_down, t_down + back, t[-1] + 1], [0, 0, 1, 1, 0, 0])
    kick_amount = np.clip(hgt / height, 0, 1)
    tr.root += (w * shift * -SIGN[side])[:, None] * left
    tr.root -= (0.06 * kick_amount)[:, None] * fwd
    tr.root[:, 1] -= 0.02 * w
    tr.pelvis[:, 1] += SIGN[side] * 0.06 * w
    tr.pelvis[:, 0] -= 0.2 * kick_amount
    tr.spine[:, 0] -= 0.15 * kick_amount
    tr.pelvis[:, 2] += SIGN[side] * 0.1 * kick_amount * 0.5
    # Kicking ankle: forward from the pelvis at its height, relative to the start spot.
    base = state.feet[side]
    ank = base + f[:, None] * fwd
    ank[:, 1] = ANKLE_HEIGHT[side] + hgt
    tr.ankle[:, side] = np.where(air[:, None], ank, tr.ankle[:, side])
    tr.foot_pitch[:, side] = np.where(air, pitch, P0)
    tr.planted[:, side] = ~air
    # Arms out to the sides for balance.
    bal = w[:, None]
    pose = np.array([rng.uniform(-0.1, 0.15), rng.uniform(0.5, 0.8), 0.0, rng.uniform(0.2, 0.5)])
    for s in (0, 1):
        tr.arm[:, s] = tr.arm[:, s] * (1 - bal) + pose * bal
    tr.arm[:, side, 0] -= 0.3 * kick_amount  # the kicking side's arm swings back
    tr.neck[:, 0] += 0.15 * kick_amount
    return tr, state


def act_punch(rng, n, state, style, params, ctx):
    hand = params["hand"]
    T = (n - 1) / FPS
    guard_in, guard_out = rng.uniform(0.3, 0.5), rng.uniform(0.3, 0.5)
    per = rng.uniform(0.45, 0.7)
    avail = T - 0.2 - guard_in - guard_out
    max_p = int(avail // per)
    if hand == "both":
        if max_p < 2:
            raise Infeasible("no room for two punches")
        count = int(rng.integers(2, min(6, max_p) + 1))
        first = int(rng.integers(2))
        order = [(first + j) % 2 for j in range(count)]
    else:
        if max_p < 1:
            raise Infeasible("no room for a punch")
        count = int(rng.integers(1, min(4, max_p) + 1))
        order = [0 if hand == "left" else 1] * count
    phases = [(guard_in, guard_in)] + [(per * 0.8, per * 1.2)] * count + [(guard_out, guard_out)]
    d, lead = _timeline_fit(rng, n, phases)
    t = np.arange(n) / FPS
    tr = standing_track(n, state, style)
    t_g = lead + d[0]
    t_end = lead + d[:-1].sum()
    g = keyframes(t, [0, lead, t_g, t_end, t_end + d[-1], t[-1] + 1], [0, 0, 1, 1, 0, 0])
    guard = np.array([rng.uniform(0.45, 0.75), rng.uniform(0.15, 0.35), 0.2, rng.uniform(1.9, 2.25)])
    _blend_arms(tr, g, guard, np.array([-0.3, 1.0, 0.3]), (0, 1))
    tr.root[:, 1] -= rng.uniform(0.02, 0.05) * g
    tc = t_g
    twist = np.zeros(n)
    for j, s in enumerate(order):
        dur = d[1 + j]
        ext, hold = dur * rng.uniform(0.25, 0.35), dur * rng.uniform(0.05, 0.15)
        k = keyframes(t, [0, tc, tc + ext, tc + ext + hold, tc + dur * 0.85, t[-1] + 1], [0, 0, 1, 1, 0, 0])
        pose = np.array([rng.uniform(1.45, 1.62), rng.uniform(0.0, 0.1), rng.uniform(0.05, 0.25), rng.uniform(0.0, 0.12)])
        kk = k[:, None]
        tr.arm[:, s] = tr.arm[:, s] * (1 - kk) + pose * kk
        tr.hint[:, s] = _normalize(tr.hint[:, s] * (1 - kk) + np.array([0.0, 1.0, 0.0]) * kk)
        twist += -SIGN[s] * rng.uniform(0.15, 0.3) * k
        tc += dur
    tr.spine[:, 2] += twist
    tr.pelvis[:, 2] += 0.3 * twist
    tr.neck[:, 1] -= 0.9 * (tr.spine[:, 2] + tr.pelvis[:, 2])
    return tr, state


def act_sit(rng, n, state, style, params, ctx, stand_up: bool | None = None):
    if stand_up is None:
        stand_up = (not ctx.last) or rng.random() < 0.4
    phases = [(0.9, 1.4), (1.0, 1.5)] + ([(1.0, 1.4)] if stand_up else [])
    d, lead = _timeline_fit(rng, n, phases, pads=(0.1, 0.6), fill=1)
    t = np.arange(n) / FPS
    tr = standing_track(n, state, style)
    H = style.height
    seat = rng.uniform(0.46, 0.55)
    back = rng.uniform(0.3, 0.42)
    t_down = lead + d[0]
    t_rise = t_down + d[1]
    if stand_up:
        t_up = t_rise + d[2]
        keys_t = [0, lead, t_down, t_rise, t_up, t[-1] + 1]
        drop = keyframes(t, keys_t, [0, 0, 1, 1, 0, 0])
        backk = keyframes(t, [0, lead, t_down - 0.3 * d[0], t_rise + 0.3 * d[2], t_up, t[-1] + 1], [0, 0, 1, 1, 0, 0])
        lean_t = [0, lead, lead + 0.5 * d[0], t_down, t_rise, t_rise + 0.45 * d[2], t_up, t[-1] + 1]
        lean_v = [0, 0, 1, 0, 0, 1, 0, 0]
    else:
        drop = keyframes(t, [0, lead, t_down, t[-1] + 1], [0, 0, 1, 1])
        backk = keyframes(t, [0, lead, t_down - 0.3 * d[0], t[-1] + 1], [0, 0, 1, 1])
        lean_t = [0, lead, lead + 0.5 * d[0], t_down, t[-1] + 1]
        lean_v = [0, 0, 1, 0, 0]
    lean = keyframes(t, lean_t, lean_v)
    fwd = forward_dir(state.heading)
    tr.root[:, 1] = H - (H - seat) * drop
    tr.root -= (back * backk)[:, None] * fwd
    tr.spine[:, 0] += rng.uniform(0.45, 0.7) * lean + rng.uniform(0.05, 0.2) * drop
    tr.pelvis[:, 0] += 0.25 * lean + 0.12 * drop
    tr.neck[:, 0] -= 0.4 * lean
    pose = np.array([rng.uniform(0.45, 0.75), 0.15, 0.05, rng.uniform(0.45, 0.9)])
    _blend_arms(tr, drop, pose, np.array([0.0, -0.3, 1.0]), (0, 1))
    return tr, state


ACTION_FUNCTIONS = {
    "stand": act_stand, "walk": act_walk, "run": act_run, "turn": act_turn, "circle": act_circle,
    "jump": act_jump, "squat": act_squat, "wave": act_wave, "raise_arms": act_raise_arms,
    "kick": act_kick, "punch": act_punch, "sit": act_sit,
}


# ----------------------------------------------------------------------------- clips


@dataclass(frozen=True)
class PartSpec:
    action: str
    params: dict
    frames: int  # feature rows of this part
    options: dict | None = None


def _add_noise(tr: Track, rng: np.random.Generator, style: Style) -> None:
    n = tr.n
    a = 0.02 * style.noise
    tr.spine += a * smooth_noise(rng, n, 10.0, 3) * np.array([1.0, 0.6, 1.0])
    tr.neck += 2 * a * smooth_noise(rng, n, 12.0, 2)
    tr.arm[:, :, :2] += a * smooth_noise(rng, n, 8.0, 4).reshape(n, 2, 2)
    tr.arm[:, :, 3] += 1.5 * a * smooth_noise(rng, n, 8.0, 2)
    tr.arm[:, :, 3] = np.maximum(tr.arm[:, :, 3], 0.0)


def make_motion(specs: list[PartSpec], rng: np.random.Generator, style: Style | None = None):
    """Joint positions (N, 22, 3) (world frame, N = total rows + 1) and the label parts."""
    quats, root, parts = make_pose(specs, rng, style)
    return pose_to_joints(quats, root), parts


def make_pose(specs: list[PartSpec], rng: np.random.Generator, style: Style | None = None):
    """Local rotations (N, 22, 4), root positions (N, 3) and label parts of a clip (see make_motion)."""
    style = Style.sample(rng) if style is None else style
    heading = rng.uniform(-np.pi, np.pi)
    state = State.standing_at(rng.uniform(-1.5, 1.5, 2), heading, style)
    track = None
    parts = []
    start = 0
    for i, spec in enumerate(specs):
        last = i == len(specs) - 1
        n = spec.frames + (1 if last else 0)
        ctx = Context(moving_start=i == 0, moving_end=last, last=last)
        fn = ACTION_FUNCTIONS[spec.action]
        kwargs = dict(spec.options or {})
        tr, state = fn(rng, n, state, style, spec.params, ctx, **kwargs)
        track = tr if track is None else concat_tracks(track, tr, int(rng.integers(5, 10)))
        parts.append({"action": spec.action, "params": dict(spec.params), "start": start, "end": start + spec.frames})
        start += spec.frames
    _add_noise(track, rng, style)
    quats, root = track_to_pose(track)
    return quats, root, parts


__all__ = [
    "ACTION_FUNCTIONS", "Context", "Gait", "Infeasible", "PartSpec", "State", "Style", "Track",
    "concat_tracks", "make_motion", "make_pose", "matrix_to_quat", "pose_to_joints", "standing_track",
    "track_to_joints", "track_to_pose",
]

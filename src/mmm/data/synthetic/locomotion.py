"""Locomotion (walk, run, turn, circle): gaits, footstep planning and the animation of a pelvis path.

Footsteps are planned from the pelvis path: each foot's stance is centred on a time of the gait
cycle and its foothold is the pelvis pose at that time plus the foot's offset, so a planted foot
never moves; the foot rolls over the heel and the toe joint (heel strike, flat, heel off), swings
to the next foothold, and the pelvis height comes from the legs: as high as the nominal height
allows and never higher than the stance legs reach (which makes it bob with the gait). Running
adds flight phases. Arms swing opposite to the legs, the pelvis and thorax counter-rotate.

Paths are given on an extended time grid (`extended_grid`: a margin before and after the part)
so that footsteps can be planned past both ends; `speed_profile` eases the speed in and out.
The walk and run gaits are `walk_gait` and `run_gait`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from mmm.data.synthetic.body import (
    ANKLE_HEIGHT,
    FOOT,
    GRAVITY,
    P0,
    SIGN,
    State,
    Style,
    foot_ankle,
    forward_dir,
    left_dir,
    normalize,
    reach_cap,
    standing_track,
    wrap_angle,
)
from mmm.data.synthetic.constants import FPS
from mmm.data.synthetic.curves import gaussian_smooth, smoothstep


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


def plan_steps(
    te,
    pos,
    yaw,
    vbody,
    gait: Gait,
    style: Style,
    n: int,
    lead: int,
    first_center: float,
    start_feet: State | None,
):
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
        still = (np.linalg.norm(np.diff(flat, axis=0), axis=-1) < 0.015) & (
            np.abs(wrap_angle(np.diff(fy))) < 0.04
        )
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
                ankle[m, side] = foot_ankle(flat_k, yaw_k, pp, side)
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
            a0 = foot_ankle(flat_k, yaw_k, np.array(p_a), side)
            a1 = foot_ankle(nxt[0], nxt[1], np.array(p_b), side)
            mh = smoothstep(u ** (1.35 if gait.running else 1.0))
            mv = smoothstep(u)
            step = float(np.linalg.norm((nxt[0] - flat_k)[[0, 2]]))
            lift = gait.lift_base + gait.lift * step
            bump = np.sin(np.pi * u**gait.swing_peak) ** 1.5
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


def speed_profile(te, t_a, t_b, ramp_in, ramp_out, moving_start, moving_end):
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


def locomotion(
    n,
    state: State,
    style: Style,
    *,
    gait: Gait,
    te,
    yaw,
    vbody,
    t_start,
    lead,
    height,
    start_standing: bool,
    sway=0.35,
    twist=0.25,
    arm_gain=1.0,
    elbow=None,
    lean=0.0,
    arm_abd=None,
    bounce=0.0,
):
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
        te, pos, yaw, vbody, gait, style, n, lead, first_center, state if start_standing else None
    )
    tr = standing_track(n, state, style)
    tr.heading = yaw[E : E + n].copy()
    root = pos[E : E + n].copy()
    tr.ankle, tr.foot_pitch, tr.foot_yaw, tr.planted = ankle, pitch, fyaw, planted
    fwd, left = forward_dir(tr.heading), left_dir(tr.heading)
    vb = vbody[E : E + n]
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
        tr.hint[:] = normalize(np.array([-0.3, 0.0, 1.0]))
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


def extended_grid(n: int, margin_s: float = 2.0):
    E = int(margin_s * FPS)
    return np.arange(-E, n + E) / FPS


def walk_gait(direction: str, v: float) -> Gait:
    if direction == "forward":
        return Gait(
            period=2 / (1.2 + 0.7 * v),
            duty=max(0.52, 0.64 - 0.055 * v),
            lift=0.035,
            lift_base=0.04,
            heel_strike=0.45,
            heel_off=0.7,
            toe_strike=0.55,
            toe_lift=0.35,
            step_ref=1.1,
            shift=0.15,
            reach=0.995,
            swing_peak=0.85,
        )
    if direction == "backward":
        return Gait(
            period=2 / (1.4 + 0.7 * v),
            duty=max(0.5, 0.62 - 0.06 * v),
            lift=0.04,
            lift_base=0.05,
            heel_strike=0.45,
            heel_off=0.6,
            toe_strike=0.6,
            toe_lift=0.4,
            step_ref=1.0,
            shift=0.15,
            reach=0.995,
            swing_peak=1.0,
        )
    return Gait(
        period=2 / (1.6 + 1.3 * v),
        duty=max(0.34, 0.62 - 0.14 * v),
        lift=0.03,
        lift_base=0.05,
        heel_strike=0.2,
        heel_off=0.3,
        toe_strike=0.3,
        toe_lift=0.2,
        step_ref=1.0,
        shift=0.0,
        reach=0.993,
        swing_peak=1.0,
    )


def run_gait(v: float) -> Gait:
    return Gait(
        period=2 / (2.6 + 0.25 * v),
        duty=0.42 - 0.025 * v,
        lift=0.1,
        lift_base=0.15,
        heel_strike=0.1,
        heel_off=0.8,
        toe_strike=0.5,
        toe_lift=0.3,
        step_ref=1.6,
        shift=0.1,
        reach=0.975,
        swing_peak=0.7,
        td_frac=0.3,
        lo_frac=0.55,
        running=True,
    )

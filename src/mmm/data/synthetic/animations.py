"""Procedural animation of each action of the synthetic vocabulary on the 22-joint skeleton.

One `act_*` function per action (stand, walk, run, turn, circle, jump, squat, wave, raise_arms,
kick, punch, sit); the action table (`table.ACTIONS`) names them. An action function takes
(rng, n, state, style, params, ctx) and returns the `Track` of its n frames and the `State` it
ends in; it raises `Infeasible` when the action does not fit n frames.
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
    UP,
    State,
    Track,
    foot_ankle,
    forward_dir,
    left_dir,
    normalize,
    standing_track,
)
from mmm.data.synthetic.constants import FPS, WALK_SPEEDS
from mmm.data.synthetic.curves import hermite, keyframes, smooth_noise, smoothstep
from mmm.data.synthetic.locomotion import Gait, extended_grid, locomotion, run_gait, speed_profile, walk_gait


class Infeasible(Exception):
    """The requested action cannot be animated in the given number of frames."""


@dataclass
class Context:
    """Where a part sits in its clip."""

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
        tr.hint[:, s] = normalize(tr.hint[:, s] * (1 - k) + normalize(np.asarray(hint, dtype=np.float64)) * k)


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


def _walk_path(rng, n, v_mean, ctx, extra_pad=(0.05, 0.35), ramp=(0.45, 0.8), vmax=2.3):
    """Speed profile on the extended grid for a walk/run of mean speed v_mean over n frames."""
    te = extended_grid(n)
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
            s = speed_profile(te, t_a, t_b, r_in, r_out, moving_start, moving_end)
            return te, s, v, t_a, not moving_start
    raise Infeasible(f"mean speed {v_mean:.2f} m/s over {T:.2f} s needs {v:.2f} m/s")


def act_walk(rng, n, state, style, params, ctx):
    direction, speed = params["direction"], params["speed"]
    lo, hi = WALK_SPEEDS[speed]
    v_mean = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo))
    te, s, v, t_a, standing = _walk_path(rng, n, v_mean, ctx)
    gait = walk_gait(direction, v)
    body = {"forward": (0.0, 1.0), "backward": (0.0, -1.0), "left": (1.0, 0.0), "right": (-1.0, 0.0)}[
        direction
    ]
    vbody = v * s[:, None] * np.array(body)
    drift = rng.uniform(-0.12, 0.12) * smoothstep((te - t_a) / max(te[-1] - t_a, 1e-6))
    yaw = state.heading + drift
    lead = {"left": 0, "right": 1}.get(direction, int(rng.integers(2)))
    lateral = direction in ("left", "right")
    h = style.height + 0.01
    tr, end = locomotion(
        n,
        state,
        style,
        gait=gait,
        te=te,
        yaw=yaw,
        vbody=vbody,
        t_start=t_a,
        lead=lead,
        height=h,
        start_standing=standing,
        arm_gain=0.0 if lateral else 1.1,
        lean=0.04 if direction == "backward" else 0.0,
        arm_abd=style.arm_abd + (0.1 if lateral else 0.0),
    )
    return tr, end


def act_run(rng, n, state, style, params, ctx):
    v_mean = rng.uniform(2.45, 3.3)
    te, s, v, t_a, standing = _walk_path(
        rng, n, v_mean, ctx, extra_pad=(0.05, 0.25), ramp=(0.55, 0.85), vmax=3.5
    )
    v = max(v, 2.5)
    gait = run_gait(v)
    vbody = v * s[:, None] * np.array([0.0, 1.0])
    yaw = state.heading + rng.uniform(-0.1, 0.1) * smoothstep((te - t_a) / max(te[-1] - t_a, 1e-6))
    E = int(round(-te[0] * FPS))
    k = s[E : E + n]
    h = style.height * (1 - k) + (style.height - 0.05 - 0.015 * (v - 2.5)) * k
    tr, end = locomotion(
        n,
        state,
        style,
        gait=gait,
        te=te,
        yaw=yaw,
        vbody=vbody,
        t_start=t_a,
        lead=int(rng.integers(2)),
        height=h,
        start_standing=standing,
        sway=0.2,
        twist=0.2,
        arm_gain=1.5,
        elbow=rng.uniform(1.35, 1.65),
        lean=rng.uniform(0.02, 0.1),
        arm_abd=style.arm_abd + 0.05,
        bounce=0.045,
    )
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
    te = extended_grid(n)
    yaw = state.heading + sign * angle * smoothstep((te - t_a) / dur)
    gait = Gait(
        period=rng.uniform(0.8, 1.0),
        duty=0.62,
        lift=0.1,
        lift_base=0.05,
        heel_strike=0.1,
        heel_off=0.3,
        toe_strike=0.2,
        toe_lift=0.1,
        step_ref=0.6,
        shift=0.0,
        reach=0.995,
        swing_peak=0.9,
    )
    vbody = np.zeros((len(te), 2))
    tr, end = locomotion(
        n,
        state,
        style,
        gait=gait,
        te=te,
        yaw=yaw,
        vbody=vbody,
        t_start=t_a - 0.15 * gait.period,
        lead=0 if sign > 0 else 1,
        height=style.height,
        start_standing=True,
        sway=0.3,
        twist=0.15,
        arm_gain=0.3,
    )
    # The head leads into the turn.
    E = int(round(-te[0] * FPS))
    lead_ang = np.interp(np.arange(n) / FPS + 0.3, te, yaw) - yaw[E : E + n]
    tr.neck[:, 1] += 0.6 * lead_ang
    tr.spine[:, 2] += 0.3 * lead_ang
    return tr, end


def act_circle(rng, n, state, style, params, ctx):
    sign = 1.0 if params["side"] == "counterclockwise" else -1.0
    T = (n - 1) / FPS
    theta = math.radians(rng.uniform(352.0, 372.0))
    te = extended_grid(n)
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
    s = speed_profile(te, t_a, t_b, r_in, r_out, False, False)
    dt = np.diff(te, prepend=te[0])
    yaw = state.heading + sign * np.cumsum(v * s * dt) / radius
    yaw = yaw - (yaw[int(round(-te[0] * FPS))] - state.heading)
    vbody = v * s[:, None] * np.array([0.0, 1.0])
    gait = walk_gait("forward", v)
    gait = replace(gait, period=gait.period * 0.8)  # shorter, quicker steps on a tight circle
    tr, end = locomotion(
        n,
        state,
        style,
        gait=gait,
        te=te,
        yaw=yaw,
        vbody=vbody,
        t_start=t_a,
        lead=0 if sign < 0 else 1,
        height=style.height + 0.01,
        start_standing=True,
        arm_gain=1.0,
    )
    E = int(round(-te[0] * FPS))
    lean = sign * 0.06 * s[E : E + n] * v / 1.5  # lean into the curve
    tr.pelvis[:, 1] += lean * 0.5
    tr.neck[:, 1] += sign * 0.15 * s[E : E + n]
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
        crouch, push, flight, land = d[i : i + 4]
        i += 4
        depth, absorb = rng.uniform(0.08, 0.19), rng.uniform(0.07, 0.17)
        y_to = H + rng.uniform(0.03, 0.055)
        v0 = GRAVITY * flight / 2
        t_cb, t_to = tcur + crouch, tcur + crouch + push
        t_ld, t_ab = t_to + flight, t_to + flight + land
        J = dists[j]
        vh = (1 - 2 * a) * J / flight
        y_knots += [(t_cb, H - depth, 0.0), (t_to, y_to, v0), (t_ld, y_to, -v0), (t_ab, H - absorb, 0.0)]
        x_knots += [
            (t_cb, x0, 0.0),
            (t_to, x0 + a * J, vh),
            (t_ld, x0 + (1 - a) * J, vh),
            (t_ab, x0 + J, 0.0),
        ]
        b = rng.uniform(0.03, 0.08)
        hb_keys += [
            (t_cb, b),
            (t_to, 0.4 * b),
            (t_to + 0.5 * flight, 0.0),
            (t_ld, 0.0),
            (t_ab, rng.uniform(0.02, 0.06)),
        ]
        flights.append((t_to, t_ld, y_to))
        takeoff.append((t_cb, t_to, t_ld, t_ab))
        arm_keys += [
            (t_cb, -rng.uniform(0.5, 0.9)),
            (t_to + 0.3 * flight, rng.uniform(1.6, 2.6)),
            (t_ab, rng.uniform(0.2, 0.5)),
        ]
        spine_keys += [
            (t_cb, rng.uniform(0.25, 0.45)),
            (t_to, rng.uniform(0.0, 0.1)),
            (t_ab, rng.uniform(0.15, 0.3)),
        ]
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
            tr.ankle[m, s] = foot_ankle(feet[s], fy[s], pp, s)
            tr.foot_pitch[m, s] = pp
            # flight: toe path from the old to the new toe spot, lifted with the pelvis
            m = (t >= t_to) & (t < t_ld)
            u = (t[m] - t_to) / (t_ld - t_to)
            h = forward_dir(fy[s])
            toe0 = feet[s] + FOOT[s] * (math.cos(P0) * h - math.sin(P0) * UP)
            toe1 = new_feet[s] + FOOT[s] * (math.cos(P0) * h - math.sin(P0) * UP)
            toe = toe0 + (toe1 - toe0) * smoothstep(u)[:, None]
            toe[:, 1] = 0.85 * (y[m] - (y[m][0] if m.any() else 0.0)) + tuck * np.sin(np.pi * u)
            pp = p_to + (p_land - p_to) * smoothstep(u)
            tr.ankle[m, s] = toe - FOOT[s] * (np.cos(pp)[:, None] * h - np.sin(pp)[:, None] * UP)
            tr.foot_pitch[m, s] = pp
            tr.planted[m, s] = False
            # landing: heel lowers about the toe
            m = t >= t_ld
            pp = p_land + (P0 - p_land) * smoothstep((t[m] - t_ld) / max(t_ab - t_ld, 0.05))
            tr.ankle[m, s] = foot_ankle(new_feet[s], fy[s], pp, s)
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
        down, hold, up = d[i : i + 3]
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
        tr.hint[:, s] = normalize(tr.hint[:, s] * (1 - kk) + hint * kk)
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
        up, hold, down = d[i : i + 3]
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
        tr.hint[:, s] = normalize(tr.hint[:, s] * (1 - k[:, None]) + normalize(hint) * k[:, None])
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
        ch, ex, ho, re = d[i : i + 4]
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
        pose = np.array(
            [rng.uniform(1.45, 1.62), rng.uniform(0.0, 0.1), rng.uniform(0.05, 0.25), rng.uniform(0.0, 0.12)]
        )
        kk = k[:, None]
        tr.arm[:, s] = tr.arm[:, s] * (1 - kk) + pose * kk
        tr.hint[:, s] = normalize(tr.hint[:, s] * (1 - kk) + np.array([0.0, 1.0, 0.0]) * kk)
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
        backk = keyframes(
            t, [0, lead, t_down - 0.3 * d[0], t_rise + 0.3 * d[2], t_up, t[-1] + 1], [0, 0, 1, 1, 0, 0]
        )
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

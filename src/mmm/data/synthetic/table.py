"""The action table of the synthetic data: one `ActionSpec` per action, gathered in `ACTIONS`.

A spec says everything about one action: how often the generator picks it, how its label
parameters are drawn, how long a part may last, how it is animated, how captions phrase it and
which conditions on the joints the adherence checker holds it to (spec: synthetic-data.md). The
generator, the caption builder and the checker look actions up here and nowhere else.

To add an action: write its animation `act_<name>` in animations.py (words its captions use go
into captions.LEXICON), then a section below with its thresholds, parameters, phrase and check,
and its `ActionSpec` row in `ACTIONS`. The rows' order and weights are part of what a seed
draws: adding or reordering an action changes the dataset generated for a given seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mmm.data.synthetic.animations import (
    act_circle,
    act_jump,
    act_kick,
    act_punch,
    act_raise_arms,
    act_run,
    act_sit,
    act_squat,
    act_stand,
    act_turn,
    act_walk,
    act_wave,
)
from mmm.data.synthetic.constants import WALK_SPEEDS
from mmm.data.synthetic.measure import (
    HEAD,
    L_WRIST,
    OTHER_SIDE,
    PELVIS,
    R_WRIST,
    SIDE_JOINTS,
    displacement,
    excursions,
    flight_frames,
    heading_change,
    initial_frame,
    mean_speed,
    root_path_length,
    runs,
)

Check = list[tuple[str, float, str, object]]  # (name, measured value, op, threshold) of each condition


def _no_params(rng: np.random.Generator) -> dict:
    return {}


def _no_options(rng: np.random.Generator, followed: bool) -> dict:
    return {}


def _two_to_six_seconds(params: dict, options: dict) -> tuple[float, float]:
    return 2.0, 6.0


@dataclass(frozen=True)
class ActionSpec:
    """Everything the generator, the caption builder and the checker know about one action."""

    name: str
    weight: float  # relative frequency of the action in the generated clips
    animate: Callable  # (rng, n, state, style, params, ctx, **options) -> (Track, State); see animations.py
    sample_params: Callable[[np.random.Generator], dict]  # label parameters, named as in the spec's Labels
    phrase: Callable[[np.random.Generator, dict, bool], str]  # (rng, params, stands_up) -> verb phrase
    check: Callable[[np.ndarray, dict, float, float], Check]  # (part's joints, params, fps, standing height)
    duration: Callable[[dict, dict], tuple[float, float]] = _two_to_six_seconds  # (params, options) -> s
    sample_options: Callable[[np.random.Generator, bool], dict] = _no_options  # (rng, followed) -> options


# ----------------------------------------------------------------------------- caption helpers
# A phrase is a verb phrase (third person, present); '{pron}' marks the subject's possessive and
# `word|TAG` a word whose part of speech differs from its LEXICON default.


def pick(rng: np.random.Generator, options):
    return options[int(rng.integers(len(options)))]


_SPEED_ADV = {
    "slow": ["slowly", "at a slow pace", "leisurely", "slowly and steadily"],
    "normal": ["", "", "at a normal pace", "at a steady pace", "at a regular pace", "steadily"],
    "fast": ["quickly", "fast", "briskly", "at a fast|ADJ pace", "rapidly", "at a quick pace"],
}
_SPEED_PRE = {"slow": ["slowly"], "normal": ["steadily", ""], "fast": ["quickly", "briskly", "rapidly"]}
_SPEED_ADJ = {
    "slow": ["slow", "short slow"],
    "normal": ["steady", "regular", "normal"],
    "fast": ["quick", "fast", "brisk", "hurried"],
}
_COUNT_ADV = {
    1: ["once", "one time", "a single time"],
    2: ["twice", "two times", "2 times"],
    3: ["three times", "3 times", "thrice"],
}
_COUNT_NOUN = {
    1: ["a single {n}", "one {n}", "a {n}"],
    2: ["two {n}s", "2 {n}s"],
    3: ["three {n}s", "3 {n}s"],
}


# ----------------------------------------------------------------------------- stand

STAND_MAX_PATH = 0.3
STAND_MAX_HEIGHT_DEVIATION = 0.1


def _stand_phrase(rng, params, stands_up):
    return pick(
        rng,
        [
            "stands still",
            "stands in place",
            "stands without moving",
            "is standing still",
            "remains standing in place",
            "stays still",
            "waits standing in one spot",
            "stands still with {pron} arms at {pron} sides|NOUN",
        ],
    )


def _stand_check(joints, params, fps, h_stand) -> Check:
    height = joints[:, PELVIS, 1]
    return [
        ("root path (m)", root_path_length(joints), "<", STAND_MAX_PATH),
        (
            "max |pelvis height - standing height| (m)",
            float(np.abs(height - h_stand).max()),
            "<=",
            STAND_MAX_HEIGHT_DEVIATION,
        ),
    ]


# ----------------------------------------------------------------------------- walk

WALK_MAX_ANGLE_DEG = 45.0


def _walk_params(rng):
    return {
        "direction": pick(rng, ["forward", "backward", "left", "right"]),
        "speed": pick(rng, ["slow", "normal", "fast"]),
    }


def _walk_duration(params, options):
    return (2.5, 6.0) if params["speed"] == "fast" else (2.0, 6.0)


def _walk_phrase(rng, params, stands_up):
    d, s = params["direction"], params["speed"]
    adv, pre, adj = pick(rng, _SPEED_ADV[s]), pick(rng, _SPEED_PRE[s]), pick(rng, _SPEED_ADJ[s])
    if d == "forward":
        opts = [
            "walks forward {adv}",
            "walks straight ahead {adv}",
            "{pre} walks forward",
            "takes {adj} steps|NOUN forward",
            "walks forwards {adv}",
            "moves forward {adv} on foot",
            "walks ahead in a straight|ADJ line {adv}",
        ]
        if s == "slow":
            opts.append("strolls forward slowly")
        if s == "fast":
            opts += ["hurries forward", "strides forward quickly"]
    elif d == "backward":
        opts = [
            "walks backward {adv}",
            "walks backwards {adv}",
            "{pre} walks backwards",
            "steps|VERB back|ADV {adv}",
            "takes {adj} steps|NOUN backward",
            "moves backward {adv}",
            "steps|VERB backwards {adv}",
        ]
    else:
        opts = [
            "walks to the {side}|NOUN {adv}",
            "sidesteps to the {side}|NOUN {adv}",
            "steps|VERB sideways to the {side}|NOUN {adv}",
            "{pre} walks sideways to {pron} {side}|NOUN",
            "shuffles sideways towards the {side}|NOUN {adv}",
            "moves to the {side}|NOUN {adv} with side|NOUN steps|NOUN",
            "takes {adj} side|NOUN steps|NOUN to the {side}|NOUN",
        ]
    return pick(rng, opts).format(adv=adv, pre=pre, adj=adj, side=d, pron="{pron}")


def _walk_check(joints, params, fps, h_stand) -> Check:
    direction = params["direction"]
    fwd, left = initial_frame(joints)
    target = {"forward": fwd, "backward": -fwd, "left": left, "right": -left}[direction]
    disp = displacement(joints)
    norm = np.linalg.norm(disp)
    cos = float(disp @ target / norm) if norm > 1e-9 else -1.0
    angle = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    return [
        (f"angle of displacement from {direction} (deg)", angle, "<=", WALK_MAX_ANGLE_DEG),
        (f"mean speed (m/s), {params['speed']}", mean_speed(joints, fps), "in", WALK_SPEEDS[params["speed"]]),
    ]


# ----------------------------------------------------------------------------- run

RUN_MIN_SPEED = 2.2
RUN_MIN_FLIGHT_PHASES = 2


def _run_phrase(rng, params, stands_up):
    return pick(
        rng,
        [
            "runs forward",
            "runs straight ahead",
            "jogs forward",
            "is running forward",
            "runs forward quickly",
            "runs ahead",
            "dashes forward",
            "jogs straight ahead",
        ],
    )


def _run_check(joints, params, fps, h_stand) -> Check:
    return [
        ("mean speed (m/s)", mean_speed(joints, fps), ">", RUN_MIN_SPEED),
        (
            "flight phases (both feet off the ground)",
            float(runs(flight_frames(joints))),
            ">=",
            RUN_MIN_FLIGHT_PHASES,
        ),
    ]


# ----------------------------------------------------------------------------- turn

TURN_MIN_FRACTION = 0.6
TURN_MAX_DISPLACEMENT = 0.5


def _turn_params(rng):
    return {"side": pick(rng, ["left", "right"]), "angle": pick(rng, [90, 180])}


def _turn_duration(params, options):
    return (2.0, 4.0) if params["angle"] == 90 else (2.8, 5.0)


def _turn_phrase(rng, params, stands_up):
    side, angle = params["side"], int(params["angle"])
    if angle == 90:
        opts = [
            "turns {s}|ADV",
            "turns to the {s}|NOUN",
            "turns ninety degrees to the {s}|NOUN",
            "turns 90 degrees to {pron} {s}|NOUN",
            "makes a quarter turn|NOUN to the {s}|NOUN",
            "rotates to {pron} {s}|NOUN",
            "pivots to the {s}|NOUN",
        ]
    else:
        opts = [
            "turns around to the {s}|NOUN",
            "turns 180 degrees to the {s}|NOUN",
            "makes a half turn|NOUN to the {s}|NOUN",
            "turns all the way around to {pron} {s}|NOUN",
            "turns around over {pron} {s}|ADJ shoulder",
            "turns around to the {s}|NOUN to|PART face the other way",
        ]
    return pick(rng, opts).format(s=side, pron="{pron}")


def _turn_check(joints, params, fps, h_stand) -> Check:
    sign = 1.0 if params["side"] == "left" else -1.0
    change = heading_change(joints) * sign
    return [
        (
            f"heading change towards the {params['side']} (deg)",
            change,
            ">=",
            TURN_MIN_FRACTION * float(params["angle"]),
        ),
        ("displacement (m)", float(np.linalg.norm(displacement(joints))), "<", TURN_MAX_DISPLACEMENT),
    ]


# ----------------------------------------------------------------------------- circle

CIRCLE_MIN_HEADING_DEG = 270.0
CIRCLE_MAX_END_DISTANCE = 1.0


def _circle_params(rng):
    return {"side": pick(rng, ["clockwise", "counterclockwise"])}


def _circle_phrase(rng, params, stands_up):
    side = params["side"]
    word = side if side == "clockwise" else pick(rng, ["counterclockwise", "anticlockwise"])
    opts = [
        "walks in a {w}|ADJ circle",
        "walks around in a circle {w}|ADV",
        "walks {w}|ADV in a circle",
        "goes around in a {w}|ADJ circle",
        "walks a full circle {w}|ADV",
        "circles around {w}|ADV",
        "walks in a circle in a {w}|ADJ direction",
    ]
    return pick(rng, opts).format(w=word)


def _circle_check(joints, params, fps, h_stand) -> Check:
    sign = 1.0 if params["side"] == "counterclockwise" else -1.0
    change = heading_change(joints) * sign
    return [
        (f"cumulative heading change, {params['side']} (deg)", change, ">=", CIRCLE_MIN_HEADING_DEG),
        (
            "end distance from the start (m)",
            float(np.linalg.norm(displacement(joints))),
            "<=",
            CIRCLE_MAX_END_DISTANCE,
        ),
    ]


# ----------------------------------------------------------------------------- jump

JUMP_MIN_PEAK = 0.15
JUMP_MIN_FORWARD_PER_JUMP = 0.4


def _jump_params(rng):
    return {"count": int(rng.integers(1, 4)), "mode": pick(rng, ["in_place", "forward"])}


def _jump_duration(params, options):
    return {1: (2.0, 4.0), 2: (2.7, 5.5), 3: (3.7, 6.0)}[params["count"]]


def _jump_phrase(rng, params, stands_up):
    count, mode = int(params["count"]), params["mode"]
    times = pick(rng, _COUNT_ADV[count])
    jumps = pick(rng, _COUNT_NOUN[count]).format(n="jump")
    if mode == "in_place":
        where = pick(rng, ["in place", "on the spot", "in the same spot", "up|ADV and down|ADV"])
        opts = [
            "jumps {where} {times}",
            "jumps {times} {where}",
            "hops {where} {times}",
            "does {jumps} {where}",
            "jumps up|ADV {times}",
        ]
    else:
        where = pick(rng, ["forward", "forwards", "ahead"])
        opts = [
            "jumps {where} {times}",
            "jumps {times} {where}",
            "hops {where} {times}",
            "leaps {where} {times}",
            "does {jumps} {where}",
            "makes {jumps} {where}",
        ]
    return pick(rng, opts).format(where=where, times=times, jumps=jumps)


def _jump_check(joints, params, fps, h_stand) -> Check:
    count = int(params["count"])
    peaks = excursions(joints[:, PELVIS, 1], h_stand + JUMP_MIN_PEAK, above=True)
    out = [(f"pelvis peaks >= standing + {JUMP_MIN_PEAK} m", float(peaks), "==", count)]
    if params.get("mode") == "forward":
        fwd, _ = initial_frame(joints)
        out.append(
            (
                "forward displacement (m)",
                float(displacement(joints) @ fwd),
                ">=",
                JUMP_MIN_FORWARD_PER_JUMP * count,
            )
        )
    return out


# ----------------------------------------------------------------------------- squat

SQUAT_MIN_DIP = 0.25


def _squat_params(rng):
    return {"count": int(rng.integers(1, 4))}


def _squat_duration(params, options):
    return {1: (2.0, 4.0), 2: (3.0, 6.0), 3: (4.2, 6.0)}[params["count"]]


def _squat_phrase(rng, params, stands_up):
    count = int(params["count"])
    times = pick(rng, _COUNT_ADV[count])
    squats = pick(rng, _COUNT_NOUN[count]).format(n="squat")
    return pick(
        rng,
        [
            "squats {times}",
            "squats down {times}",
            "does {squats}",
            "performs {squats}",
            "bends {pron} knees and squats {times}",
            "squats down and stands|VERB back|ADV up|ADV {times}",
        ],
    ).format(times=times, squats=squats, pron="{pron}")


def _squat_check(joints, params, fps, h_stand) -> Check:
    dips = excursions(joints[:, PELVIS, 1], h_stand - SQUAT_MIN_DIP, above=False)
    return [(f"pelvis dips <= standing - {SQUAT_MIN_DIP} m", float(dips), "==", int(params["count"]))]


# ----------------------------------------------------------------------------- wave

WAVE_MIN_FRACTION = 0.4


def _hand_params(rng):  # wave and punch
    return {"hand": pick(rng, ["left", "right", "both"])}


def _wave_phrase(rng, params, stands_up):
    hand = params["hand"]
    if hand == "both":
        return pick(
            rng,
            [
                "waves both hands",
                "waves with both arms",
                "raises both hands and waves them",
                "waves both arms over {pron} head",
                "waves with both hands above {pron} head",
            ],
        )
    return pick(
        rng,
        [
            "waves {pron} {h}|ADJ hand",
            "waves with {pron} {h}|ADJ hand",
            "raises {pron} {h}|ADJ hand and waves",
            "waves the {h}|ADJ arm above {pron} head",
            "lifts the {h}|ADJ hand and waves it",
        ],
    ).format(h=hand, pron="{pron}")


def _wave_check(joints, params, fps, h_stand) -> Check:
    hand = params["hand"]
    out = []
    for side in ("left", "right") if hand == "both" else (hand,):
        wrist = SIDE_JOINTS[side][3]
        frac = float(np.mean(joints[:, wrist, 1] > joints[:, HEAD, 1]))
        out.append(
            (f"fraction of frames with the {side} wrist above the head", frac, ">=", WAVE_MIN_FRACTION)
        )
    if hand != "both":
        other = OTHER_SIDE[hand]
        _, _, shoulder, wrist = SIDE_JOINTS[other]
        over = float((joints[:, wrist, 1] - joints[:, shoulder, 1]).max())
        out.append((f"max height of the {other} wrist above its shoulder (m)", over, "<", 0.0))
    return out


# ----------------------------------------------------------------------------- raise_arms

RAISE_MIN_FRACTION = 0.3


def _raise_arms_phrase(rng, params, stands_up):
    return pick(
        rng,
        [
            "raises both arms",
            "raises {pron} arms above {pron} head",
            "lifts {pron} arms up|ADV",
            "puts {pron} hands up|ADV in the air",
            "raises {pron} hands over {pron} head",
            "holds {pron} arms up|ADV above {pron} head",
            "lifts both arms into the air",
        ],
    )


def _raise_arms_check(joints, params, fps, h_stand) -> Check:
    above = (joints[:, L_WRIST, 1] > joints[:, HEAD, 1]) & (joints[:, R_WRIST, 1] > joints[:, HEAD, 1])
    return [
        (
            "fraction of frames with both wrists above the head",
            float(np.mean(above)),
            ">=",
            RAISE_MIN_FRACTION,
        )
    ]


# ----------------------------------------------------------------------------- kick

KICK_MIN_HEIGHT = 0.5
KICK_MIN_AHEAD = 0.3
KICK_MAX_OTHER_HEIGHT = 0.2


def _kick_params(rng):
    return {"foot": pick(rng, ["left", "right"])}


def _kick_phrase(rng, params, stands_up):
    f = params["foot"]
    return pick(
        rng,
        [
            "kicks with {pron} {f}|ADJ foot",
            "kicks forward with the {f}|ADJ leg",
            "does a kick|NOUN with {pron} {f}|ADJ leg",
            "kicks {pron} {f}|ADJ leg forward",
            "performs a front|ADJ kick|NOUN with the {f}|ADJ foot",
            "kicks something in front|NOUN with {pron} {f}|ADJ foot",
        ],
    ).format(f=f, pron="{pron}")


def _kick_check(joints, params, fps, h_stand) -> Check:
    foot = params["foot"]
    fwd, _ = initial_frame(joints)
    toe = SIDE_JOINTS[foot][1]
    height = joints[:, toe, 1]
    ahead = (joints[:, toe][:, [0, 2]] - joints[:, PELVIS][:, [0, 2]]) @ fwd
    # The frame where the kick best meets both conditions, so that both are read on one frame.
    best = int(np.argmax(np.minimum(height - KICK_MIN_HEIGHT, ahead - KICK_MIN_AHEAD)))
    other = OTHER_SIDE[foot]
    ankle_o, toe_o = SIDE_JOINTS[other][:2]
    return [
        (f"{foot} foot height at its best frame (m)", float(height[best]), ">=", KICK_MIN_HEIGHT),
        (f"{foot} foot ahead of the pelvis at that frame (m)", float(ahead[best]), ">=", KICK_MIN_AHEAD),
        (
            f"max height of the {other} foot (m)",
            float(joints[:, [ankle_o, toe_o], 1].max()),
            "<",
            KICK_MAX_OTHER_HEIGHT,
        ),
    ]


# ----------------------------------------------------------------------------- punch

PUNCH_MIN_AHEAD = 0.4
PUNCH_MAX_HEIGHT_OFFSET = 0.2


def _punch_phrase(rng, params, stands_up):
    hand = params["hand"]
    if hand == "both":
        return pick(
            rng,
            [
                "punches with both hands",
                "throws punches|NOUN with both fists",
                "punches forward with both arms alternately",
                "boxes with both hands",
                "throws punches|NOUN with {pron} left|ADJ and right|ADJ fists",
            ],
        )
    return pick(
        rng,
        [
            "punches forward with {pron} {h}|ADJ hand",
            "throws a punch|NOUN with {pron} {h}|ADJ fist",
            "punches with the {h}|ADJ arm",
            "punches straight ahead with {pron} {h}|ADJ fist",
            "throws punches|NOUN with the {h}|ADJ hand",
        ],
    ).format(h=hand, pron="{pron}")


def _punch_check(joints, params, fps, h_stand) -> Check:
    hand = params["hand"]
    fwd, _ = initial_frame(joints)
    out = []
    for side in ("left", "right") if hand == "both" else (hand,):
        _, _, shoulder, wrist = SIDE_JOINTS[side]
        ahead = (joints[:, wrist][:, [0, 2]] - joints[:, shoulder][:, [0, 2]]) @ fwd
        offset = np.abs(joints[:, wrist, 1] - joints[:, shoulder, 1])
        best = int(np.argmax(np.minimum(ahead - PUNCH_MIN_AHEAD, PUNCH_MAX_HEIGHT_OFFSET - offset)))
        out.append(
            (
                f"{side} wrist ahead of its shoulder at its best frame (m)",
                float(ahead[best]),
                ">=",
                PUNCH_MIN_AHEAD,
            )
        )
        out.append(
            (
                f"{side} wrist height offset from its shoulder at that frame (m)",
                float(offset[best]),
                "<=",
                PUNCH_MAX_HEIGHT_OFFSET,
            )
        )
    return out


# ----------------------------------------------------------------------------- sit

SIT_MAX_PELVIS = 0.6
SIT_MIN_FRACTION = 0.4


def _sit_options(rng, followed):
    # A sit that is followed by something must stand up again.
    return {"stand_up": followed or bool(rng.random() < 0.4)}


def _sit_duration(params, options):
    return (3.6, 6.0) if options.get("stand_up") else (3.0, 6.0)


def _sit_phrase(rng, params, stands_up):
    if stands_up:
        return pick(
            rng,
            [
                "sits down on a chair and gets back|ADV up|ADV",
                "sits down briefly and stands|VERB up|ADV again",
                "takes a seat and stands|VERB up|ADV again",
                "sits on a chair and then rises",
                "sits down and stands|VERB back|ADV up|ADV",
            ],
        )
    return pick(
        rng,
        [
            "sits down",
            "sits down on a chair",
            "takes a seat",
            "sits on a chair",
            "lowers {pron}self onto a seat|NOUN",
        ],
    )


def _sit_check(joints, params, fps, h_stand) -> Check:
    frac = float(np.mean(joints[:, PELVIS, 1] <= SIT_MAX_PELVIS))
    return [(f"fraction of frames with the pelvis <= {SIT_MAX_PELVIS} m", frac, ">=", SIT_MIN_FRACTION)]


# ----------------------------------------------------------------------------- the table

ACTIONS: dict[str, ActionSpec] = {
    spec.name: spec
    for spec in (
        ActionSpec("stand", 1.0, act_stand, _no_params, _stand_phrase, _stand_check),
        ActionSpec("walk", 3.0, act_walk, _walk_params, _walk_phrase, _walk_check, duration=_walk_duration),
        ActionSpec(
            "run",
            1.0,
            act_run,
            lambda rng: {"direction": "forward"},
            _run_phrase,
            _run_check,
            duration=lambda params, options: (2.5, 6.0),
        ),
        ActionSpec("turn", 1.2, act_turn, _turn_params, _turn_phrase, _turn_check, duration=_turn_duration),
        ActionSpec(
            "circle",
            0.9,
            act_circle,
            _circle_params,
            _circle_phrase,
            _circle_check,
            duration=lambda params, options: (4.3, 6.0),
        ),
        ActionSpec("jump", 1.2, act_jump, _jump_params, _jump_phrase, _jump_check, duration=_jump_duration),
        ActionSpec(
            "squat", 1.0, act_squat, _squat_params, _squat_phrase, _squat_check, duration=_squat_duration
        ),
        ActionSpec("wave", 1.0, act_wave, _hand_params, _wave_phrase, _wave_check),
        ActionSpec("raise_arms", 0.9, act_raise_arms, _no_params, _raise_arms_phrase, _raise_arms_check),
        ActionSpec("kick", 1.0, act_kick, _kick_params, _kick_phrase, _kick_check),
        ActionSpec("punch", 1.0, act_punch, _hand_params, _punch_phrase, _punch_check),
        ActionSpec(
            "sit",
            1.0,
            act_sit,
            _no_params,
            _sit_phrase,
            _sit_check,
            duration=_sit_duration,
            sample_options=_sit_options,
        ),
    )
}

__all__ = ["ACTIONS", "ActionSpec", "pick"]

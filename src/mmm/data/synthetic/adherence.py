"""Prompt-adherence checker: does a motion do what its label says?

Every action of the synthetic vocabulary (spec: synthetic-data.md) comes with conditions on the
joint positions; `check_motion` evaluates them on each labelled part of a motion and reports every
condition with its measured value and threshold, so a failure says what went wrong.

Joints are (T, 22, 3) in the canonical frame of `recover_from_ric` (y up, metres, floor at the
lowest point of the motion, frame 0 facing +Z, +X the body's left). Facing per frame comes from
the hips and shoulders: across = (R_hip - L_hip) + (R_shoulder - L_shoulder), forward = up × across.
Heading angles grow when turning left (+Z towards +X, counter-clockwise seen from above).

Measurement choices (the thresholds themselves are the spec's):
- speeds are horizontal root (pelvis) speeds; the mean speed of a part is its root path length
  divided by its duration, (frames - 1) / fps;
- "the direction" / "ahead" are taken in the part's initial heading frame: the facing averaged
  over the part's first 3 frames;
- peaks and dips are excursions past the threshold, with a 2 cm hysteresis so that noise around
  the threshold does not split one peak into two;
- a frame is airborne (a flight phase of a run) when both feet are off the ground: every foot
  joint (ankle, toe) more than 3 cm above the floor;
- "near shoulder height" for a punch is within 0.2 m of the shoulder's height.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mmm.data.arrays import load_array
from mmm.motion.skeleton import T2M_SKELETON, Skeleton

FPS = 20.0

# Joint indices of the 22-joint skeleton.
PELVIS, L_HIP, R_HIP = 0, 1, 2
L_ANKLE, R_ANKLE, L_TOE, R_TOE = 7, 8, 10, 11
HEAD, L_SHOULDER, R_SHOULDER, L_WRIST, R_WRIST = 15, 16, 17, 20, 21
SIDE_JOINTS = {  # side -> (ankle, toe, shoulder, wrist)
    "left": (L_ANKLE, L_TOE, L_SHOULDER, L_WRIST),
    "right": (R_ANKLE, R_TOE, R_SHOULDER, R_WRIST),
}
OTHER_SIDE = {"left": "right", "right": "left"}

# Neutral standing pose (shared with the animation in body.py): the foot bone (ankle -> toe
# joint) points forward and down by this angle with the toe joint on the floor, and the knees
# are nearly straight (hip-to-ankle distance = STAND_REACH × leg length).
NEUTRAL_FOOT_PITCH = math.radians(22.0)
STAND_REACH = 0.997
# The pelvis->hip bones point out and down by this angle, as in HumanML3D (54 degrees on the
# reference sample): the hips sit ~0.085 m below the pelvis joint, which lifts the pelvis.
HIP_DROP = math.radians(54.0)

# Thresholds of the spec's table.
WALK_SPEEDS = {"slow": (0.5, 0.8), "normal": (1.0, 1.4), "fast": (1.6, 2.0)}
STAND_MAX_PATH = 0.3
STAND_MAX_HEIGHT_DEVIATION = 0.1
WALK_MAX_ANGLE_DEG = 45.0
RUN_MIN_SPEED = 2.2
RUN_MIN_FLIGHT_PHASES = 2
TURN_MIN_FRACTION = 0.6
TURN_MAX_DISPLACEMENT = 0.5
CIRCLE_MIN_HEADING_DEG = 270.0
CIRCLE_MAX_END_DISTANCE = 1.0
JUMP_MIN_PEAK = 0.15
JUMP_MIN_FORWARD_PER_JUMP = 0.4
SQUAT_MIN_DIP = 0.25
WAVE_MIN_FRACTION = 0.4
RAISE_MIN_FRACTION = 0.3
KICK_MIN_HEIGHT = 0.5
KICK_MIN_AHEAD = 0.3
KICK_MAX_OTHER_HEIGHT = 0.2
PUNCH_MIN_AHEAD = 0.4
PUNCH_MAX_HEIGHT_OFFSET = 0.2
SIT_MAX_PELVIS = 0.6
SIT_MIN_FRACTION = 0.4
# Measurement constants (not thresholds of the table).
HYSTERESIS = 0.02
FLIGHT_CLEARANCE = 0.03
HEADING_FRAMES = 3

ACTIONS = ("stand", "walk", "run", "turn", "circle", "jump", "squat", "wave", "raise_arms", "kick", "punch", "sit")


def standing_height(skeleton: Skeleton = T2M_SKELETON) -> float:
    """Pelvis height (m) of the neutral standing pose, from the skeleton's bone lengths.

    Hips HIP_DROP below the pelvis, legs nearly straight (STAND_REACH of hip->knee + knee->ankle)
    above ankles that sit foot_length · sin(NEUTRAL_FOOT_PITCH) above the toe joints on the
    floor; mean of both sides. About 0.96 m for the HumanML3D target skeleton.
    """
    lengths = skeleton.bone_lengths
    if lengths is None or skeleton.num_joints != 22:
        raise ValueError(f"standing_height needs the 22-joint skeleton with target bone lengths, got {skeleton.name!r}")
    heights = []
    for pelvis_hip, hip_knee, knee_ankle, ankle_toe in ((1, 4, 7, 10), (2, 5, 8, 11)):
        leg = lengths[hip_knee] + lengths[knee_ankle]
        drop = lengths[pelvis_hip] * math.sin(HIP_DROP)
        heights.append(drop + STAND_REACH * leg + lengths[ankle_toe] * math.sin(NEUTRAL_FOOT_PITCH))
    return float(np.mean(heights))


STANDING_HEIGHT = standing_height()


@dataclass(frozen=True)
class Condition:
    """One checked condition of one labelled part."""

    part: int
    action: str
    name: str
    value: float
    op: str  # one of "<", "<=", ">", ">=", "==", "in"
    threshold: float | tuple[float, float]
    passed: bool

    def __str__(self) -> str:
        thr = f"[{self.threshold[0]:g}, {self.threshold[1]:g}]" if isinstance(self.threshold, tuple) else f"{self.threshold:g}"
        mark = "ok  " if self.passed else "FAIL"
        return f"{mark} part {self.part} {self.action}: {self.name} = {self.value:.3f} (needs {self.op} {thr})"


@dataclass
class AdherenceResult:
    """All conditions of all parts; `passed` when every one holds."""

    conditions: list[Condition] = field(default_factory=list)
    part_passed: list[bool] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(self.part_passed) and bool(self.part_passed)

    @property
    def failures(self) -> list[Condition]:
        return [c for c in self.conditions if not c.passed]

    def __str__(self) -> str:
        head = "passed" if self.passed else f"failed ({len(self.failures)} of {len(self.conditions)} conditions)"
        return "\n".join([head] + [f"  {c}" for c in self.conditions])


def _compare(value: float, op: str, threshold) -> bool:
    if not np.isfinite(value):
        return False
    if op == "<":
        return value < threshold
    if op == "<=":
        return value <= threshold
    if op == ">":
        return value > threshold
    if op == ">=":
        return value >= threshold
    if op == "==":
        return value == threshold
    if op == "in":
        return threshold[0] <= value <= threshold[1]
    raise ValueError(f"unknown comparison {op!r}")


def facing_vectors(joints: np.ndarray) -> np.ndarray:
    """Horizontal unit facing directions (T, 2) as (x, z) from hips and shoulders of (T, 22, 3)."""
    across = (joints[:, R_HIP] - joints[:, L_HIP]) + (joints[:, R_SHOULDER] - joints[:, L_SHOULDER])
    fwd = np.stack((across[:, 2], -across[:, 0]), axis=-1)  # up × across, (x, z)
    return fwd / np.maximum(np.linalg.norm(fwd, axis=-1, keepdims=True), 1e-9)


def heading_angles(joints: np.ndarray) -> np.ndarray:
    """Unwrapped heading (T,) in radians, increasing when turning left (+Z towards +X)."""
    fwd = facing_vectors(joints)
    return np.unwrap(np.arctan2(fwd[:, 0], fwd[:, 1]))


def _initial_frame(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward and left unit vectors (x, z) of the part's initial heading."""
    fwd = facing_vectors(joints[:HEADING_FRAMES]).mean(axis=0)
    fwd = fwd / max(np.linalg.norm(fwd), 1e-9)
    left = np.array([fwd[1], -fwd[0]])  # forward turned by +90 degrees (+Z -> +X)
    return fwd, left


def _excursions(signal: np.ndarray, threshold: float, above: bool) -> int:
    """Number of excursions past `threshold` (above or below), with HYSTERESIS to leave one."""
    count, inside = 0, False
    for v in signal:
        if not inside and ((v >= threshold) if above else (v <= threshold)):
            count, inside = count + 1, True
        elif inside and ((v < threshold - HYSTERESIS) if above else (v > threshold + HYSTERESIS)):
            inside = False
    return count


def _runs(mask: np.ndarray) -> int:
    """Number of maximal runs of True."""
    m = np.asarray(mask, dtype=bool)
    if m.size == 0:
        return 0
    return int(m[0]) + int(np.count_nonzero(m[1:] & ~m[:-1]))


def root_path_length(joints: np.ndarray) -> float:
    xz = joints[:, PELVIS][:, [0, 2]]
    return float(np.linalg.norm(np.diff(xz, axis=0), axis=-1).sum())


def mean_speed(joints: np.ndarray, fps: float = FPS) -> float:
    n = joints.shape[0]
    return root_path_length(joints) * fps / max(n - 1, 1)


def flight_frames(joints: np.ndarray) -> np.ndarray:
    """(T,) bool: both feet off the ground (every foot joint above FLIGHT_CLEARANCE)."""
    feet = joints[:, [L_ANKLE, L_TOE, R_ANKLE, R_TOE], 1]
    return feet.min(axis=-1) > FLIGHT_CLEARANCE


def _check_part(joints: np.ndarray, action: str, params: dict, fps: float, h_stand: float) -> list[tuple[str, float, str, object]]:
    """(name, value, op, threshold) of each condition of one part; joints are the part's frames."""
    pelvis = joints[:, PELVIS]
    xz = pelvis[:, [0, 2]]
    disp = xz[-1] - xz[0]
    out: list[tuple[str, float, str, object]] = []
    if action == "stand":
        out.append(("root path (m)", root_path_length(joints), "<", STAND_MAX_PATH))
        out.append(("max |pelvis height - standing height| (m)", float(np.abs(pelvis[:, 1] - h_stand).max()), "<=", STAND_MAX_HEIGHT_DEVIATION))
    elif action == "walk":
        direction = params["direction"]
        fwd, left = _initial_frame(joints)
        target = {"forward": fwd, "backward": -fwd, "left": left, "right": -left}[direction]
        norm = np.linalg.norm(disp)
        cos = float(disp @ target / norm) if norm > 1e-9 else -1.0
        angle = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
        out.append((f"angle of displacement from {direction} (deg)", angle, "<=", WALK_MAX_ANGLE_DEG))
        out.append((f"mean speed (m/s), {params['speed']}", mean_speed(joints, fps), "in", WALK_SPEEDS[params["speed"]]))
    elif action == "run":
        out.append(("mean speed (m/s)", mean_speed(joints, fps), ">", RUN_MIN_SPEED))
        out.append(("flight phases (both feet off the ground)", float(_runs(flight_frames(joints))), ">=", RUN_MIN_FLIGHT_PHASES))
    elif action == "turn":
        sign = 1.0 if params["side"] == "left" else -1.0
        heading = heading_angles(joints)
        k = min(HEADING_FRAMES, len(heading))
        change = math.degrees(heading[-k:].mean() - heading[:k].mean()) * sign
        out.append((f"heading change towards the {params['side']} (deg)", change, ">=", TURN_MIN_FRACTION * float(params["angle"])))
        out.append(("displacement (m)", float(np.linalg.norm(disp)), "<", TURN_MAX_DISPLACEMENT))
    elif action == "circle":
        sign = 1.0 if params["side"] == "counterclockwise" else -1.0
        heading = heading_angles(joints)
        k = min(HEADING_FRAMES, len(heading))
        change = math.degrees(heading[-k:].mean() - heading[:k].mean()) * sign
        out.append((f"cumulative heading change, {params['side']} (deg)", change, ">=", CIRCLE_MIN_HEADING_DEG))
        out.append(("end distance from the start (m)", float(np.linalg.norm(disp)), "<=", CIRCLE_MAX_END_DISTANCE))
    elif action == "jump":
        count = int(params["count"])
        peaks = _excursions(pelvis[:, 1], h_stand + JUMP_MIN_PEAK, above=True)
        out.append((f"pelvis peaks >= standing + {JUMP_MIN_PEAK} m", float(peaks), "==", count))
        if params.get("mode") == "forward":
            fwd, _ = _initial_frame(joints)
            out.append(("forward displacement (m)", float(disp @ fwd), ">=", JUMP_MIN_FORWARD_PER_JUMP * count))
    elif action == "squat":
        dips = _excursions(pelvis[:, 1], h_stand - SQUAT_MIN_DIP, above=False)
        out.append((f"pelvis dips <= standing - {SQUAT_MIN_DIP} m", float(dips), "==", int(params["count"])))
    elif action == "wave":
        hand = params["hand"]
        sides = ("left", "right") if hand == "both" else (hand,)
        for side in sides:
            wrist = SIDE_JOINTS[side][3]
            frac = float(np.mean(joints[:, wrist, 1] > joints[:, HEAD, 1]))
            out.append((f"fraction of frames with the {side} wrist above the head", frac, ">=", WAVE_MIN_FRACTION))
        if hand != "both":
            other = OTHER_SIDE[hand]
            _, _, shoulder, wrist = SIDE_JOINTS[other]
            over = float((joints[:, wrist, 1] - joints[:, shoulder, 1]).max())
            out.append((f"max height of the {other} wrist above its shoulder (m)", over, "<", 0.0))
    elif action == "raise_arms":
        above = (joints[:, L_WRIST, 1] > joints[:, HEAD, 1]) & (joints[:, R_WRIST, 1] > joints[:, HEAD, 1])
        out.append(("fraction of frames with both wrists above the head", float(np.mean(above)), ">=", RAISE_MIN_FRACTION))
    elif action == "kick":
        foot = params["foot"]
        fwd, _ = _initial_frame(joints)
        toe = SIDE_JOINTS[foot][1]
        height = joints[:, toe, 1]
        ahead = (joints[:, toe][:, [0, 2]] - xz) @ fwd
        best = int(np.argmax(np.minimum(height - KICK_MIN_HEIGHT, ahead - KICK_MIN_AHEAD)))
        out.append((f"{foot} foot height at its best frame (m)", float(height[best]), ">=", KICK_MIN_HEIGHT))
        out.append((f"{foot} foot ahead of the pelvis at that frame (m)", float(ahead[best]), ">=", KICK_MIN_AHEAD))
        other = OTHER_SIDE[foot]
        ankle_o, toe_o = SIDE_JOINTS[other][:2]
        out.append((f"max height of the {other} foot (m)", float(joints[:, [ankle_o, toe_o], 1].max()), "<", KICK_MAX_OTHER_HEIGHT))
    elif action == "punch":
        hand = params["hand"]
        fwd, _ = _initial_frame(joints)
        for side in (("left", "right") if hand == "both" else (hand,)):
            _, _, shoulder, wrist = SIDE_JOINTS[side]
            ahead = (joints[:, wrist][:, [0, 2]] - joints[:, shoulder][:, [0, 2]]) @ fwd
            offset = np.abs(joints[:, wrist, 1] - joints[:, shoulder, 1])
            best = int(np.argmax(np.minimum(ahead - PUNCH_MIN_AHEAD, PUNCH_MAX_HEIGHT_OFFSET - offset)))
            out.append((f"{side} wrist ahead of its shoulder at its best frame (m)", float(ahead[best]), ">=", PUNCH_MIN_AHEAD))
            out.append((f"{side} wrist height offset from its shoulder at that frame (m)", float(offset[best]), "<=", PUNCH_MAX_HEIGHT_OFFSET))
    elif action == "sit":
        frac = float(np.mean(pelvis[:, 1] <= SIT_MAX_PELVIS))
        out.append((f"fraction of frames with the pelvis <= {SIT_MAX_PELVIS} m", frac, ">=", SIT_MIN_FRACTION))
    else:
        raise ValueError(f"unknown action {action!r}; expected one of {', '.join(ACTIONS)}")
    return out


def check_motion(joints, parts: list[dict], fps: float = FPS, standing: float | None = None) -> AdherenceResult:
    """Check each labelled part of a motion against its action's conditions.

    joints: (T, 22, 3) in the canonical frame (numpy or torch).
    parts: label parts, dicts with "action", "params", "start", "end" (frame indices, end exclusive).
    standing: standing pelvis height; `standing_height()` of the target skeleton by default.
    """
    joints = np.asarray(joints.detach().cpu().numpy() if hasattr(joints, "detach") else joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (22, 3):
        raise ValueError(f"joints must be (T, 22, 3), got {joints.shape}")
    h_stand = STANDING_HEIGHT if standing is None else float(standing)
    result = AdherenceResult()
    for i, part in enumerate(parts):
        start, end = int(part["start"]), int(part["end"])
        if not (0 <= start < end <= joints.shape[0]) or end - start < 2:
            raise ValueError(f"part {i} ({part.get('action')}) has frames [{start}, {end}) outside the motion's {joints.shape[0]} frames")
        ok = True
        for name, value, op, thr in _check_part(joints[start:end], part["action"], part.get("params", {}), fps, h_stand):
            passed = _compare(value, op, thr)
            ok &= passed
            result.conditions.append(Condition(i, part["action"], name, float(value), op, thr, passed))
        result.part_passed.append(ok)
    return result


def check_dataset(root, split: str = "test") -> tuple[float, dict[str, float]]:
    """Fraction of the split's clips whose joints satisfy all their labels, and per action the
    fraction of labelled parts that pass. Reads `<root>/<split>.txt`, `labels/` and `new_joints/`."""
    root = Path(root)
    split_file = root / f"{split}.txt"
    if not split_file.exists():
        raise FileNotFoundError(f"{split_file} does not exist; generate the dataset first (mmm data synth --out {root})")
    ids = [line.strip() for line in split_file.read_text().splitlines() if line.strip()]
    if not ids:
        raise ValueError(f"{split_file} lists no clips")
    clip_ok = []
    per_action: dict[str, list[bool]] = {}
    for motion_id in ids:
        label = json.loads((root / "labels" / f"{motion_id}.json").read_text())
        joints = load_array(root / "new_joints" / f"{motion_id}.npy", "clip's joints (T, 22, 3)", f"generate the dataset again (mmm data synth --out {root})")
        res = check_motion(joints, label["parts"], fps=label.get("fps", FPS))
        clip_ok.append(res.passed)
        for part, ok in zip(label["parts"], res.part_passed):
            per_action.setdefault(part["action"], []).append(ok)
    return float(np.mean(clip_ok)), {a: float(np.mean(v)) for a, v in sorted(per_action.items())}


__all__ = [
    "ACTIONS", "AdherenceResult", "Condition", "check_dataset", "check_motion", "facing_vectors",
    "flight_frames", "heading_angles", "mean_speed", "root_path_length", "standing_height",
    "STANDING_HEIGHT", "NEUTRAL_FOOT_PITCH", "HIP_DROP", "WALK_SPEEDS",
]

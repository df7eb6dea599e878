"""Prompt-adherence checker: does a motion do what its label says?

Every action of the synthetic vocabulary (spec: synthetic-data.md) comes with conditions on the
joint positions (its spec's `check` in the action table, table.py); `check_motion` evaluates them
on each labelled part of a motion and reports every condition with its measured value and
threshold, so a failure says what went wrong.

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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mmm.data.arrays import load_array
from mmm.data.synthetic.constants import (  # noqa: F401 (re-exported: the checker's standing pose)
    FPS,
    HIP_DROP,
    NEUTRAL_FOOT_PITCH,
    STAND_REACH,
    STANDING_HEIGHT,
    WALK_SPEEDS,
    standing_height,
)
from mmm.data.synthetic.measure import (  # noqa: F401 (re-exported: what the checker measures)
    facing_vectors,
    flight_frames,
    heading_angles,
    mean_speed,
    root_path_length,
)

# The thresholds live with their actions in the table; re-exported for the callers of the checker.
from mmm.data.synthetic.table import (  # noqa: F401
    ACTIONS,
    CIRCLE_MAX_END_DISTANCE,
    CIRCLE_MIN_HEADING_DEG,
    JUMP_MIN_FORWARD_PER_JUMP,
    JUMP_MIN_PEAK,
    KICK_MAX_OTHER_HEIGHT,
    KICK_MIN_AHEAD,
    KICK_MIN_HEIGHT,
    PUNCH_MAX_HEIGHT_OFFSET,
    PUNCH_MIN_AHEAD,
    RAISE_MIN_FRACTION,
    RUN_MIN_FLIGHT_PHASES,
    RUN_MIN_SPEED,
    SIT_MAX_PELVIS,
    SIT_MIN_FRACTION,
    SQUAT_MIN_DIP,
    STAND_MAX_HEIGHT_DEVIATION,
    STAND_MAX_PATH,
    TURN_MAX_DISPLACEMENT,
    TURN_MIN_FRACTION,
    WALK_MAX_ANGLE_DEG,
    WAVE_MIN_FRACTION,
)


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
        if isinstance(self.threshold, tuple):
            thr = f"[{self.threshold[0]:g}, {self.threshold[1]:g}]"
        else:
            thr = f"{self.threshold:g}"
        mark = "ok  " if self.passed else "FAIL"
        return (
            f"{mark} part {self.part} {self.action}: {self.name} = {self.value:.3f} (needs {self.op} {thr})"
        )


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
        failed = f"failed ({len(self.failures)} of {len(self.conditions)} conditions)"
        head = "passed" if self.passed else failed
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


def check_motion(
    joints, parts: list[dict], fps: float = FPS, standing: float | None = None
) -> AdherenceResult:
    """Check each labelled part of a motion against its action's conditions.

    joints: (T, 22, 3) in the canonical frame (numpy or torch).
    parts: label parts, dicts with "action", "params", "start", "end" (frame indices, end exclusive).
    standing: standing pelvis height; `standing_height()` of the target skeleton by default.
    """
    if hasattr(joints, "detach"):
        joints = joints.detach().cpu().numpy()
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (22, 3):
        raise ValueError(f"joints must be (T, 22, 3), got {joints.shape}")
    h_stand = STANDING_HEIGHT if standing is None else float(standing)
    result = AdherenceResult()
    for i, part in enumerate(parts):
        start, end = int(part["start"]), int(part["end"])
        if not (0 <= start < end <= joints.shape[0]) or end - start < 2:
            raise ValueError(
                f"part {i} ({part.get('action')}) has frames [{start}, {end}) outside the "
                f"motion's {joints.shape[0]} frames"
            )
        spec = ACTIONS.get(part["action"])
        if spec is None:
            raise ValueError(f"unknown action {part['action']!r}; expected one of {', '.join(ACTIONS)}")
        ok = True
        for name, value, op, thr in spec.check(joints[start:end], part.get("params", {}), fps, h_stand):
            passed = _compare(value, op, thr)
            ok &= passed
            result.conditions.append(Condition(i, part["action"], name, float(value), op, thr, passed))
        result.part_passed.append(ok)
    return result


def check_in_order(
    joints,
    parts: list[dict],
    min_frames: int = 40,
    step: int = 4,
    fps: float = FPS,
    standing: float | None = None,
) -> list[int] | None:
    """The order-aware check of a composition: the frames where parts 2..k begin, for the first
    split of the motion into consecutive pieces (one per labelled part, in the label's order, each
    at least `min_frames` long) on which every part's action passes; None when no split does.

    A caption such as "walks, then jumps" says the order of its actions, not the frame where the
    second begins, so `check_motion` on the labelled spans is stricter than the caption. Splits are
    tried every `step` frames (the tokenizer's unit). One part: [] when it passes on the whole motion.
    """
    if hasattr(joints, "detach"):
        joints = joints.detach().cpu().numpy()
    joints = np.asarray(joints, dtype=np.float64)
    total = joints.shape[0]

    def search(first: int, index: int) -> list[int] | None:
        rest = len(parts) - index
        if rest == 1:
            piece = {**parts[index], "start": 0, "end": total - first}
            return [] if total - first >= min_frames and _passes(joints[first:], piece) else None
        for cut in range(first + min_frames, total - (rest - 1) * min_frames + 1, step):
            piece = {**parts[index], "start": 0, "end": cut - first}
            if _passes(joints[first:cut], piece):
                later = search(cut, index + 1)
                if later is not None:
                    return [cut, *later]
        return None

    def _passes(piece_joints, part) -> bool:
        return check_motion(piece_joints, [part], fps=fps, standing=standing).passed

    if not parts:
        return None
    return search(0, 0)


def check_dataset(root, split: str = "test") -> tuple[float, dict[str, float]]:
    """Fraction of the split's clips whose joints satisfy all their labels, and per action the
    fraction of labelled parts that pass. Reads `<root>/<split>.txt`, `labels/` and `new_joints/`."""
    root = Path(root)
    split_file = root / f"{split}.txt"
    if not split_file.exists():
        raise FileNotFoundError(
            f"{split_file} does not exist; generate the dataset first (mmm data synth --out {root})"
        )
    ids = [line.strip() for line in split_file.read_text().splitlines() if line.strip()]
    if not ids:
        raise ValueError(f"{split_file} lists no clips")
    clip_ok = []
    per_action: dict[str, list[bool]] = {}
    for motion_id in ids:
        label = json.loads((root / "labels" / f"{motion_id}.json").read_text())
        joints = load_array(
            root / "new_joints" / f"{motion_id}.npy",
            "clip's joints (T, 22, 3)",
            f"generate the dataset again (mmm data synth --out {root})",
        )
        res = check_motion(joints, label["parts"], fps=label.get("fps", FPS))
        clip_ok.append(res.passed)
        for part, ok in zip(label["parts"], res.part_passed):
            per_action.setdefault(part["action"], []).append(ok)
    return float(np.mean(clip_ok)), {a: float(np.mean(v)) for a, v in sorted(per_action.items())}


__all__ = [
    "ACTIONS",
    "AdherenceResult",
    "Condition",
    "check_dataset",
    "check_motion",
    "facing_vectors",
    "flight_frames",
    "heading_angles",
    "mean_speed",
    "root_path_length",
    "standing_height",
    "STANDING_HEIGHT",
    "NEUTRAL_FOOT_PITCH",
    "HIP_DROP",
    "WALK_SPEEDS",
]

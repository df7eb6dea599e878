"""The clips of the synthetic data: `PartSpec`, and `make_pose` / `make_motion`, which chain the
animations of a clip's parts (looked up in the action table, `table.ACTIONS`) into one track and
turn it into joint rotations or positions.

The rest lives in sibling modules; the names their callers used from here are re-exported:
- `table`: one spec per action (animation, parameters, captions, adherence check);
- `animations`: the `act_*` function of each action, `Context`, `Infeasible`;
- `body`: the skeleton and body constants, `Style`, `State`, `Track` and the kinematics
  (`track_to_pose`, `pose_to_joints`, `track_to_joints`);
- `locomotion`: gaits, footstep planning and `locomotion` (walk, run, turn, circle);
- `curves`: easing, keyframes, smoothing and noise over time;
- `constants`: `FPS` and the constants the animation shares with the checker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmm.data.synthetic.animations import Context, Infeasible
from mmm.data.synthetic.body import (
    State,
    Style,
    Track,
    concat_tracks,
    matrix_to_quat,
    pose_to_joints,
    standing_track,
    track_to_joints,
    track_to_pose,
)
from mmm.data.synthetic.constants import FPS
from mmm.data.synthetic.curves import smooth_noise
from mmm.data.synthetic.locomotion import Gait
from mmm.data.synthetic.table import ACTIONS


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
        kwargs = dict(spec.options or {})
        tr, state = ACTIONS[spec.action].animate(rng, n, state, style, spec.params, ctx, **kwargs)
        track = tr if track is None else concat_tracks(track, tr, int(rng.integers(5, 10)))
        parts.append(
            {"action": spec.action, "params": dict(spec.params), "start": start, "end": start + spec.frames}
        )
        start += spec.frames
    _add_noise(track, rng, style)
    quats, root = track_to_pose(track)
    return quats, root, parts


__all__ = [
    "Context",
    "FPS",
    "Gait",
    "Infeasible",
    "PartSpec",
    "State",
    "Style",
    "Track",
    "concat_tracks",
    "make_motion",
    "make_pose",
    "matrix_to_quat",
    "pose_to_joints",
    "standing_track",
    "track_to_joints",
    "track_to_pose",
]

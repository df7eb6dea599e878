"""Render a few clips of a dataset to look at: one per action when the dataset has labels."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from mmm.data.arrays import DataError, load_array
from mmm.data.humanml3d import FEATURE_SKELETONS, load_motion, read_captions, read_split
from mmm.motion.features import recover_from_ric
from mmm.render import render_frames, render_gif

log = logging.getLogger(__name__)


def pick_clips(root: Path, split: str, count: int) -> list[str]:
    """Up to `count` ids of a split, covering distinct first actions when labels/ exists."""
    ids = [i for i in read_split(root, split) if not i.startswith("M")] or read_split(root, split)
    label_dir = root / "labels"
    if not label_dir.is_dir():
        return ids[:count]
    chosen, seen = [], set()
    for motion_id in ids:
        path = label_dir / f"{motion_id}.json"
        if not path.exists():
            continue
        parts = json.loads(path.read_text())["parts"]
        key = tuple(p["action"] for p in parts)
        if key[0] not in seen:
            seen.add(key[0])
            chosen.append(motion_id)
        if len(chosen) == count:
            break
    return chosen or ids[:count]


def clip_joints(root: Path, motion_id: str) -> tuple[np.ndarray, bool]:
    """The clip's joints (T, J, 3) from new_joints/, or else recovered from its features in
    new_joint_vecs/ (T, J, 3) (datasets shipped without joints); True when recovered."""
    joints = root / "new_joints" / f"{motion_id}.npy"
    if joints.exists():
        return load_array(joints, "clip's joints", "regenerate the dataset's new_joints/"), False
    features = root / "new_joint_vecs" / f"{motion_id}.npy"
    if not features.exists():
        raise DataError(
            joints,
            "the clip has neither joints nor features (new_joint_vecs/ either)",
            "restore one of them, or remove the id from the split",
        )
    width = load_array(features, "clip's features", mmap_mode="r").shape[-1]
    # load_motion checks the shape and NaN/Inf; an unknown width is reported against HumanML3D's
    dim = width if width in FEATURE_SKELETONS else 263
    return recover_from_ric(load_motion(features, dim)), True


def preview_dataset(root: str | Path, out: str | Path, count: int = 6, split: str = "test") -> list[Path]:
    """One GIF per chosen clip (joints with its first caption) and a PNG contact sheet of all."""
    root, out = Path(root), Path(out)
    # Everything is read (and a bad caption file refused) before the output folder is made.
    chosen, recovered = [], []
    for motion_id in pick_clips(root, split, count):
        joints, from_features = clip_joints(root, motion_id)
        recovered += [motion_id] if from_features else []
        chosen.append((motion_id, joints, read_captions(root / "texts" / f"{motion_id}.txt")[0].text))
    if recovered:
        log.info(
            "%d of %d clips have no new_joints/ file (%s): their joints are recovered from new_joint_vecs/",
            len(recovered),
            len(chosen),
            ", ".join(recovered[:3]) + (", ..." if len(recovered) > 3 else ""),
        )
    out.mkdir(parents=True, exist_ok=True)
    motions, captions, written = [], [], []
    for motion_id, joints, caption in chosen:
        motions.append(joints)
        captions.append(f"{motion_id}: {caption}")
        written.append(render_gif([joints], out / f"{motion_id}.gif", captions=[caption]))
    if motions:
        written.append(render_frames(motions, out / "contact_sheet.png", captions=captions))
    return written

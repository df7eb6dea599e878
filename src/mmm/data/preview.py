"""Render a few clips of a dataset to look at: one per action when the dataset has labels."""

from __future__ import annotations

import json
from pathlib import Path

from mmm.data.arrays import load_array
from mmm.data.humanml3d import read_captions, read_split
from mmm.render import render_frames, render_gif


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


def preview_dataset(root: str | Path, out: str | Path, count: int = 6, split: str = "test") -> list[Path]:
    """One GIF per chosen clip (joints with its first caption) and a PNG contact sheet of all."""
    root, out = Path(root), Path(out)
    # Everything is read (and a bad caption file refused) before the output folder is made.
    chosen = [
        (
            motion_id,
            load_array(
                root / "new_joints" / f"{motion_id}.npy",
                "clip's joints",
                "regenerate the dataset's new_joints/",
            ),
            read_captions(root / "texts" / f"{motion_id}.txt")[0].text,
        )
        for motion_id in pick_clips(root, split, count)
    ]
    out.mkdir(parents=True, exist_ok=True)
    motions, captions, written = [], [], []
    for motion_id, joints, caption in chosen:
        motions.append(joints)
        captions.append(f"{motion_id}: {caption}")
        written.append(render_gif([joints], out / f"{motion_id}.gif", captions=[caption]))
    if motions:
        written.append(render_frames(motions, out / "contact_sheet.png", captions=captions))
    return written

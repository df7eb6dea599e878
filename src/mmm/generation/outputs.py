"""Write generated motions: one folder per sample, all or nothing.

    DIR/<k>/features.npy   (T, 263) float32, un-normalized
    DIR/<k>/joints.npy     (T, 22, 3) float32
    DIR/<k>/motion.gif     stick figure with the prompt (motion.mp4 too when an encoder is installed)
    DIR/<k>/motion.bvh     skeleton animation (imports in Blender)
    DIR/<k>/meta.json      prompt, length, seed, model identity, sampling settings, timings

Samples are written into a staging folder inside DIR and moved into place only when every one
of them is complete, so an error leaves no partial sample folder behind.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _write_sample(folder: Path, features: np.ndarray, joints: np.ndarray, caption: str, meta: dict, skeleton) -> None:
    from mmm.export.bvh import write_bvh
    from mmm.render import render_gif, render_mp4

    folder.mkdir(parents=True)
    np.save(folder / "features.npy", features.astype(np.float32))
    np.save(folder / "joints.npy", joints.astype(np.float32))
    render_gif([joints], folder / "motion.gif", captions=[caption], fps=skeleton.fps)
    mp4 = render_mp4([joints], folder / "motion.mp4", captions=[caption], fps=skeleton.fps)
    info = write_bvh(joints, folder / "motion.bvh", skeleton=skeleton, fps=skeleton.fps)
    meta = {**meta, "files": sorted(p.name for p in folder.iterdir()) + ["meta.json"], "mp4": mp4 is not None,
            "bvh_max_deviation_m": round(float(info.max_deviation_m), 6)}
    (folder / "meta.json").write_text(json.dumps(meta, indent=2, default=_jsonable))


def _jsonable(value):
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def write_samples(out_dir: str | Path, samples: list[dict], skeleton, overwrite: bool = False) -> list[Path]:
    """samples: dicts with features, joints, caption, meta. Returns the sample folders DIR/0, DIR/1, ..."""
    out = Path(out_dir)
    targets = [out / str(k) for k in range(len(samples))]
    taken = [t for t in targets if t.exists()]
    if taken and not overwrite:
        raise FileExistsError(f"{taken[0]} already exists; choose another --out or pass --overwrite")
    created = not out.exists()
    staging = out / f".partial-{os.getpid()}"
    try:
        for k, sample in enumerate(samples):
            _write_sample(staging / str(k), sample["features"], sample["joints"], sample["caption"], sample["meta"], skeleton)
        for k, target in enumerate(targets):
            if target.exists():
                shutil.rmtree(target)
            os.replace(staging / str(k), target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if created and out.exists() and not any(out.iterdir()):
            out.rmdir()
    return targets

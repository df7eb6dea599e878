"""Write generated motions: one folder per sample, all or nothing.

    DIR/<k>/features.npy   (T, 263) float32, un-normalized
    DIR/<k>/joints.npy     (T, 22, 3) float32
    DIR/<k>/motion.gif     stick figure with the prompt (motion.mp4 too when an encoder is installed)
    DIR/<k>/with_source.gif  edits: the source motion beside the edited one
    DIR/<k>/motion.bvh     skeleton animation (imports in Blender)
    DIR/<k>/meta.json      prompt, length, seed, model identity, sampling settings, timings

Samples are written into a temporary sibling folder (`.DIR.new-*`, beside DIR on the same file
system) and put in place only when every one of them is complete, so an error or a kill leaves
no partial sample folder behind. A new DIR appears whole, by one rename. `overwrite=True` replaces
an existing DIR whole: the old folder is renamed away (`.DIR.old-*`), the new one renamed in, the
old one deleted; a reader never sees old and new samples mixed, nor an old DIR/k beyond the new
count. Only a folder of samples is replaced: one holding anything else is refused.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from mmm.atomic import fsync_directory
from mmm.export.bvh import write_bvh
from mmm.render import render_gif, render_mp4

log = logging.getLogger(__name__)


def _write_sample(
    folder: Path,
    features: np.ndarray,
    joints: np.ndarray,
    caption: str,
    meta: dict,
    skeleton,
    reference: tuple[np.ndarray, str] | None = None,
    spans: list[tuple[int, int, str]] | None = None,
) -> None:
    """reference: (joints, caption) of the motion an edit started from, drawn beside it; spans:
    the (first frame, end frame, prompt) parts of a long motion, named under it as they play."""
    folder.mkdir(parents=True)
    np.save(folder / "features.npy", features.astype(np.float32))
    np.save(folder / "joints.npy", joints.astype(np.float32))
    render_gif(
        [joints],
        folder / "motion.gif",
        captions=[caption],
        fps=skeleton.fps,
        spans=[spans] if spans else None,
    )
    if reference is not None:
        render_gif(
            [reference[0], joints],
            folder / "with_source.gif",
            captions=[reference[1], caption],
            fps=skeleton.fps,
        )
    mp4 = render_mp4([joints], folder / "motion.mp4", captions=[caption], fps=skeleton.fps)
    info = write_bvh(joints, folder / "motion.bvh", skeleton=skeleton, fps=skeleton.fps)
    meta = {
        **meta,
        "caption": caption,  # the GIF's; `mmm render` of the sample's .npy files shows it too
        "files": sorted(p.name for p in folder.iterdir()) + ["meta.json"],
        "mp4": mp4 is not None,
        "bvh_max_deviation_m": round(float(info.max_deviation_m), 6),
    }
    (folder / "meta.json").write_text(json.dumps(meta, indent=2, default=_jsonable))


def _jsonable(value):
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


# What the generation commands write into DIR besides the sample folders (DIR/k): --trace's plot.
COMMAND_FILES = ("decoding_trace.png",)


def _is_sample_folder(path: Path) -> bool:
    return path.name.isdigit() and path.is_dir()


def _replaceable(entry: Path) -> bool:
    """Whether `entry` of an output folder is this package's: a sample folder, a command's file,
    or an earlier version's staging folder left by a killed process."""
    return _is_sample_folder(entry) or entry.name in COMMAND_FILES or entry.name.startswith(".partial-")


def _swap_in(new: Path, target: Path) -> None:
    """Put folder `new` at `target`, replacing target's old folder whole (it is renamed away
    first and deleted after; if the second rename fails the old folder is put back)."""
    old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
    os.rename(target, old / target.name)
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(old / target.name, target)
        shutil.rmtree(old, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)


def write_samples(out_dir: str | Path, samples: list[dict], skeleton, overwrite: bool = False) -> list[Path]:
    """samples: dicts with features, joints, caption, meta (and, for edits, reference: (joints,
    caption) of the source; for long motions, spans: (first frame, end frame, prompt) per
    segment). Returns the sample folders DIR/0, DIR/1, ...

    DIR may be absent (created whole), hold only this package's files (replaced whole, see the
    module docstring; earlier samples only with `overwrite`), or hold other files and no sample
    folder (the new sample folders are moved in beside them)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} is a file, not a folder; choose another --out")
    entries = sorted(out.iterdir()) if out.exists() else []
    earlier = [e for e in entries if _is_sample_folder(e)]
    if earlier and not overwrite:
        raise FileExistsError(f"{earlier[0]} already exists; choose another --out or pass --overwrite")
    foreign = [e.name for e in entries if not _replaceable(e)]
    if earlier and foreign:
        raise FileExistsError(
            f"{out} holds {', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''} besides samples; "
            "--overwrite replaces the whole "
            "folder, so it only replaces a folder of samples: move those away or choose another --out"
        )
    target = Path(os.path.abspath(out))  # a name and a parent to rename in, also for `--out .`
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.new-", dir=target.parent))
    try:
        os.chmod(staging, 0o755)  # mkdtemp creates 0700; --out gets the usual folder permissions
        for k, sample in enumerate(samples):
            _write_sample(
                staging / str(k),
                sample["features"],
                sample["joints"],
                sample["caption"],
                sample["meta"],
                skeleton,
                sample.get("reference"),
                sample.get("spans"),
            )
        if not target.exists():
            os.rename(staging, target)
        elif not foreign:  # only this package's files (or none): replaced whole
            _swap_in(staging, target)
        else:  # a folder of other things and no samples: the new sample folders are moved in
            for k in range(len(samples)):
                os.rename(staging / str(k), target / str(k))
        fsync_directory(target.parent)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return [out / str(k) for k in range(len(samples))]

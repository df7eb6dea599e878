"""Run folders under an output directory: one per training run, holding its checkpoints."""

from __future__ import annotations

import os
import time
import uuid
from contextlib import contextmanager
from pathlib import Path

RUN_DIR_ENV = "MMM_RUN_DIR"


def run_directory(output_dir: str | Path) -> Path:
    """A new run folder, the same in every process of a distributed run.

    Processes that Lightning launches inherit MMM_RUN_DIR from the first one; processes started
    by torchrun or SLURM derive the name from the job id.
    """
    if os.environ.get(RUN_DIR_ENV):
        return Path(os.environ[RUN_DIR_ENV])
    job = os.environ.get("TORCHELASTIC_RUN_ID") or os.environ.get("SLURM_JOB_ID")
    name = f"job-{job}" if job and job != "none" else time.strftime("%Y%m%d-%H%M%S") + "-" + uuid.uuid4().hex[:6]
    return Path(output_dir).resolve() / name


@contextmanager
def shared_run_directory(path: Path):
    """Expose `path` to the processes launched inside this block (DDP children)."""
    previous = os.environ.get(RUN_DIR_ENV)
    os.environ[RUN_DIR_ENV] = str(path)
    try:
        yield path
    finally:
        if previous is None:
            os.environ.pop(RUN_DIR_ENV, None)
        else:
            os.environ[RUN_DIR_ENV] = previous


def find_last_checkpoint(output_dir: str | Path) -> Path:
    """The newest `last.ckpt` under output_dir/*/checkpoints/."""
    candidates = sorted(Path(output_dir).glob("*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime)
    if not candidates:
        raise FileNotFoundError(f"{output_dir}: no */checkpoints/last.ckpt to resume from; train first or pass --resume PATH")
    return candidates[-1]

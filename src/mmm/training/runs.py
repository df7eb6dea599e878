"""Run folders under an output directory: one per training run, holding its checkpoints.

A training holds an exclusive lock on `<run folder>/.lock` (fcntl.flock) while it writes there, so
`--resume last` never picks a run another process is still writing, and two resumes never write
into one folder. The lock goes with the process: a killed training leaves no stale lock.
"""

from __future__ import annotations

import fcntl
import logging
import os
import time
import uuid
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger(__name__)

RUN_DIR_ENV = "MMM_RUN_DIR"
LOCK_NAME = ".lock"


def launch_id() -> str | None:
    """What every process of one launch shares and two launches differ in, or None outside
    torchrun/SLURM. torchrun: its run id (a fresh uuid with --standalone) and the rendezvous
    port (two launches at once on one host need different ports); SLURM: job id and step id
    (each `srun` in an allocation is its own step)."""
    run = os.environ.get("TORCHELASTIC_RUN_ID")
    if run and run != "none":
        port = os.environ.get("MASTER_PORT")
        return f"{run}-{port}" if port else run
    job, step = os.environ.get("SLURM_JOB_ID"), os.environ.get("SLURM_STEP_ID")
    if job and step:
        return f"{job}.{step}"
    return None


def is_launching_process() -> bool:
    """True in the process that owns the run folder: global rank 0 of a torchrun/SLURM launch,
    or the process that Lightning launches its DDP children from (they inherit MMM_RUN_DIR)."""
    if os.environ.get(RUN_DIR_ENV):
        return False
    return all(
        int(os.environ.get(name) or 0) == 0 for name in ("RANK", "SLURM_PROCID", "LOCAL_RANK", "NODE_RANK")
    )


def run_directory(output_dir: str | Path) -> Path:
    """A new run folder, the same in every process of a distributed run.

    Processes that Lightning launches inherit MMM_RUN_DIR from the first one; processes started
    by torchrun or SLURM derive the name from `launch_id()` (so two launches in one allocation
    differ); otherwise the time and a random suffix.
    """
    if os.environ.get(RUN_DIR_ENV):
        return Path(os.environ[RUN_DIR_ENV])
    launch = launch_id()
    name = f"job-{launch}" if launch else time.strftime("%Y%m%d-%H%M%S") + "-" + uuid.uuid4().hex[:6]
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


class RunLock:
    """An exclusive flock on `<run_dir>/.lock`, holding the owner's launch id (or pid) as text."""

    def __init__(self, run_dir: Path, handle):
        self.run_dir, self._handle = run_dir, handle

    @classmethod
    def try_acquire(cls, run_dir: Path) -> "RunLock | None":
        """The lock, or None when another process holds it."""
        run_dir.mkdir(parents=True, exist_ok=True)
        handle = open(run_dir / LOCK_NAME, "a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            return None
        handle.seek(0)
        handle.truncate()
        handle.write(f"{launch_id() or f'pid-{os.getpid()}'}\n")
        handle.flush()
        return cls(run_dir, handle)

    def release(self) -> None:
        if self._handle is not None:
            self._handle.close()  # closing the file releases the flock
            self._handle = None


def _busy_owner(run_dir: Path) -> str | None:
    """Who holds `run_dir`'s lock (its recorded launch id), or None when nobody does."""
    if not (run_dir / LOCK_NAME).exists():
        return None
    lock = RunLock.try_acquire(run_dir)
    if lock is not None:
        lock.release()
        return None
    try:
        return (run_dir / LOCK_NAME).read_text().strip() or "another process"
    except OSError:
        return "another process"


def find_last_checkpoint(output_dir: str | Path) -> Path:
    """The newest `last.ckpt` under output_dir/*/checkpoints/ whose run no other process is
    writing (those are skipped, and said so). Ranks other than the launching one accept the run
    their own launch holds."""
    candidates = sorted(
        Path(output_dir).glob("*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime, reverse=True
    )
    if not candidates:
        raise FileNotFoundError(
            f"{output_dir}: no */checkpoints/last.ckpt to resume from; train first or pass --resume PATH"
        )
    ours = launch_id()
    for path in candidates:
        owner = _busy_owner(path.parent.parent)
        if owner is None or (ours is not None and owner == ours and not is_launching_process()):
            return path
        log.warning("--resume last: skipping %s, which %s is still writing", path.parent.parent, owner)
    raise FileNotFoundError(
        f"{output_dir}: every run with a last.ckpt is still being written by another training "
        f"({', '.join(str(p.parent.parent.name) for p in candidates)}); wait for it to finish or pass "
        "--resume PATH"
    )


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.relative_to(folder)
        return True
    except ValueError:
        return False


def resume_target(resume: str, output_dir: str | Path) -> tuple[Path, Path]:
    """(checkpoint to load, run folder to write into) for `--resume last|PATH`.

    `last` and a checkpoint of a run folder of this stage (`<output_dir>/<run>/checkpoints/x.ckpt`)
    continue that run folder. Any other checkpoint is only read: the resumed run writes into a new
    run folder under output_dir, never beside the file. DDP children take the folder their
    launcher chose (MMM_RUN_DIR).
    """
    output_dir = Path(output_dir).resolve()
    inherited = os.environ.get(RUN_DIR_ENV)
    if resume == "last":
        if inherited:
            return Path(inherited) / "checkpoints" / "last.ckpt", Path(inherited)
        checkpoint = find_last_checkpoint(output_dir).resolve()
        return checkpoint, checkpoint.parent.parent
    checkpoint = Path(resume).expanduser().resolve()
    if not checkpoint.is_file():
        raise FileNotFoundError(
            f"--resume {resume}: no such checkpoint file; pass `last` or the path of a .ckpt file"
        )
    if inherited:
        return checkpoint, Path(inherited)
    if checkpoint.parent.name == "checkpoints" and checkpoint.parent.parent.parent == output_dir:
        return checkpoint, checkpoint.parent.parent
    where = "outside" if not _inside(checkpoint, output_dir) else "not in a run folder of"
    run_dir = run_directory(output_dir)
    log.info(
        "--resume %s: the checkpoint is %s %s; it is read only and the run continues in %s",
        checkpoint,
        where,
        output_dir,
        run_dir,
    )
    return checkpoint, run_dir


def claim_run_directory(run_dir: Path, resuming: bool) -> RunLock | None:
    """Lock `run_dir` for this training (the launching process only; None in the others).

    Refused when another process is writing it, or when a new run would land in a folder that
    already holds checkpoints (a second launch with the same torchrun/SLURM ids)."""
    if not is_launching_process():
        return None
    lock = RunLock.try_acquire(run_dir)
    if lock is None:
        owner = _busy_owner(run_dir) or "another process"
        raise FileExistsError(
            f"{run_dir}: {owner} is still training in this run folder; wait for it to finish, or resume "
            "another run"
        )
    if not resuming and any((run_dir / "checkpoints").glob("*.ckpt")):
        lock.release()
        raise FileExistsError(
            f"{run_dir}: a new run would write over the checkpoints of an earlier launch with the same id "
            f"({run_dir.name}); "
            "resume it with --resume last, or give this launch its own id (torchrun --rdzv-id, a new srun "
            "step)"
        )
    return lock


def discard_unused_run_directory(run_dir: Path) -> bool:
    """Remove `run_dir` when it holds nothing but its lock file (a fit that failed before writing
    anything, e.g. a refused resume); True when removed. A folder with anything else in it is kept."""
    try:
        entries = list(run_dir.iterdir())
    except FileNotFoundError:
        return False
    if any(entry.name != LOCK_NAME for entry in entries):
        return False
    for entry in entries:
        entry.unlink(missing_ok=True)
    try:
        run_dir.rmdir()
    except OSError:  # another process wrote into it meanwhile
        return False
    return True

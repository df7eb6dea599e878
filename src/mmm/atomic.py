"""Writes that a later run can trust: a file appears under its real name only when complete.

Every writer here puts the data into a temporary file in the destination folder (never $TMPDIR,
which may be another file system where a rename becomes a copy), flushes and fsyncs it, renames
it over the real name with os.replace (atomic on POSIX: a reader sees the old file or the new one,
never a mix) and fsyncs the folder so the rename itself survives a power cut. A crash or an error
before the rename leaves the old file untouched; the temporary file is removed on errors (a
SIGKILL can leave one behind, named `.<name>.<host>-<pid>.<random>.tmp`, which `remove_stale_temporaries`
clears once its writer is gone).

    with atomic_write("out/stats.json", "w") as fh:
        json.dump(stats, fh)
    atomic_write_bytes("out/weights.bin", data)
"""

from __future__ import annotations

import hashlib
import os
import socket
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Iterator

TEMP_SUFFIX = ".tmp"


def _temp_prefix(path: Path) -> str:
    # The host and pid in the name let a later writer tell a dead writer's leftovers from a live one's.
    return f".{path.name}.{socket.gethostname()}-{os.getpid()}."


def fsync_directory(folder: str | Path) -> None:
    """Make a rename or a new entry in `folder` durable (a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems (and Windows) refuse fsync on a folder; the rename is still atomic
    finally:
        os.close(fd)


@contextmanager
def atomic_write(path: str | Path, mode: str = "wb", encoding: str | None = None) -> Iterator[IO]:
    """An open temporary file beside `path`; on a clean exit it is fsynced and renamed to `path`.
    On an exception the temporary file is removed and `path` keeps its old content (or stays absent)."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write writes a whole file: mode 'w' or 'wb', not {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=_temp_prefix(path), suffix=TEMP_SUFFIX)
    try:
        with os.fdopen(fd, mode, encoding=encoding if "b" not in mode else None) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; the real file gets the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    fsync_directory(path.parent)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_write(path, "wb") as fh:
        fh.write(data)


def atomic_write_text(path: str | Path, text: str, encoding: str = "utf-8") -> None:
    with atomic_write(path, "w", encoding=encoding) as fh:
        fh.write(text)


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove the temporary files of `path` (see the module docstring) whose writer, a process on
    this host, no longer runs: what a SIGKILL during a write left behind. Returns what was removed."""
    path = Path(path)
    host = socket.gethostname()
    removed = []
    ours = (
        f".{path.name}.{host}-"  # another machine's files are left alone: no way to tell if their writer runs
    )
    for candidate in path.parent.glob(f"{ours}*{TEMP_SUFFIX}"):
        pid = candidate.name[len(ours) :].split(".", 1)[0]
        if not pid.isdigit() or _running(int(pid)):
            continue
        try:
            candidate.unlink()
            removed.append(candidate)
        except FileNotFoundError:
            pass
    return removed


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


@contextmanager
def file_lock(path: str | Path) -> Iterator[None]:
    """An exclusive advisory lock (fcntl.flock) on `path`, created if absent, held for the block.
    The kernel releases it when its process dies, so a killed holder never blocks the next one.
    Where fcntl does not exist (Windows) the block runs unlocked."""
    try:
        import fcntl  # optional: POSIX only
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)

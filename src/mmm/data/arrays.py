"""Reading numeric arrays from user files: one place where a .npy/.npz becomes numbers or a clear error.

    features = load_array("motion.npy", "source motion", "give a (T, 263) features or (T, 22, 3) joints .npy")

np.load runs with allow_pickle=False (an object array, which could run code, is refused), and
the result must hold numbers: a string, bytes or object array is refused too. A missing file, a
folder, a truncated or foreign file is a DataError (a ValueError: the CLI exits 2) naming the
file, what was expected and the fix.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np


class DataError(ValueError):
    """Bad data on disk; the message names the file, the problem and the fix."""

    def __init__(self, path: str | Path, problem: str, fix: str = ""):
        self.path, self.problem, self.fix = str(path), problem, fix
        super().__init__(f"{path}: {problem}" + (f"; {fix}" if fix else ""))


NUMERIC_KINDS = "biuf"  # bool, int, unsigned, float (numpy dtype.kind)


def _check_file(path: Path, what: str, fix: str) -> None:
    if not path.exists():
        raise DataError(path, f"no such file (expected the {what})", fix)
    if path.is_dir():
        raise DataError(path, f"is a folder, not the {what} file", fix)
    if not path.is_file():  # a FIFO or a device would block or never end
        raise DataError(path, f"is not a regular file (expected the {what})", fix)


def _reason(e: Exception) -> str:
    """Why np.load failed, in a line (numpy's advice for pickled data, to load it unsafely, is not
    repeated)."""
    if "allow_pickle" in str(e):
        return (
            "it holds pickled objects or is no .npy file at all; pickles are never loaded here (they could "
            "run code)"
        )
    lines = str(e).strip().splitlines()
    return lines[0][:200] if lines else type(e).__name__


def _check_numeric(arr: np.ndarray, path: Path, what: str, fix: str, name: str = "") -> np.ndarray:
    if arr.dtype.kind not in NUMERIC_KINDS:
        where = f" entry {name!r}" if name else ""
        raise DataError(path, f"the {what}{where} holds {arr.dtype} values, not numbers", fix)
    return arr


def load_array(
    path: str | Path, what: str, fix: str = "write it again with numpy.save", mmap_mode: str | None = None
) -> np.ndarray:
    """The numeric array in a .npy file (np.load with allow_pickle=False), or a DataError naming it."""
    path = Path(path)
    _check_file(path, what, fix)
    try:
        arr = np.load(path, allow_pickle=False, mmap_mode=mmap_mode)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise DataError(path, f"not a readable .npy array for the {what} ({_reason(e)})", fix) from None
    if not isinstance(arr, np.ndarray):  # an .npz archive: several arrays
        arr.close()
        raise DataError(path, f"is an .npz archive of several arrays, not the {what} (.npy)", fix)
    return _check_numeric(arr, path, what, fix)


def load_arrays(
    path: str | Path, what: str, fix: str = "write it again with numpy.savez"
) -> dict[str, np.ndarray]:
    """Every array of an .npz archive, read in full and checked numeric, or a DataError naming it
    (a truncated archive fails on opening or on its first damaged entry)."""
    path = Path(path)
    _check_file(path, what, fix)
    try:
        data = np.load(path, allow_pickle=False)
        if isinstance(data, np.ndarray):
            raise DataError(path, f"is a single .npy array, not the {what} (.npz)", fix)
        with data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        if isinstance(e, DataError):
            raise
        raise DataError(path, f"not a readable .npz archive for the {what} ({_reason(e)})", fix) from None
    for name, arr in arrays.items():
        _check_numeric(arr, path, what, fix, name)
    return arrays

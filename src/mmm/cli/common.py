"""What the command modules share: the error type, the parser class, .npy input and output."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

DEFAULT_TRACKING_URI = "sqlite:///mlflow.db"


class CLIError(Exception):
    pass


class Parser(argparse.ArgumentParser):
    """An ArgumentParser that adds some options only when it parses or prints its help: those
    that come from modules importing torch (the sampling options), so that building the whole
    parser, and `mmm --help`, stays fast. Its subparsers are Parsers too."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._deferred = []

    def defer(self, add) -> None:
        """Call add(self) before this parser first parses or prints anything."""
        self._deferred.append(add)

    def _add_deferred(self) -> None:
        while self._deferred:
            self._deferred.pop(0)(self)

    def parse_known_args(self, args=None, namespace=None):
        self._add_deferred()
        return super().parse_known_args(args, namespace)

    def format_usage(self):
        self._add_deferred()
        return super().format_usage()

    def format_help(self):
        self._add_deferred()
        return super().format_help()


def load_npy(path: str) -> np.ndarray:
    """A motion .npy (numbers only, never unpickled); DataError naming the file otherwise."""
    # imported here: keeps `mmm --help` fast (the data modules import torch)
    from mmm.data.arrays import DataError, load_array

    fix = "give a .npy of features (T, 263) or joints (T, 22, 3) written with numpy.save"
    array = load_array(path, "motion (.npy of features or joints)", fix)
    if array.dtype.kind == "b":  # numbers to numpy, but true/false is no motion (a mask saved by mistake?)
        raise DataError(path, "holds bool values (true/false), not motion numbers", fix)
    return array


def refuse_existing(path: str | Path, overwrite: bool, instead: str = "path") -> None:
    """CLIError when the file `path` exists and --overwrite was not given: nothing is replaced
    unasked (a folder there is refused by the writer itself). `instead`: what else to choose."""
    if not overwrite and Path(path).is_file():
        raise CLIError(f"{path} already exists: give --overwrite to replace it, or choose another {instead}")


def save_npy(path: str, array: np.ndarray) -> None:
    from mmm.data.humanml3d import save_array_atomic

    out = Path(path)
    if out.is_dir():
        raise CLIError(f"{out} is a folder: name the .npy file to write, e.g. {out / 'motion.npy'}")
    blocking = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise CLIError(f"cannot write {out}: {blocking} is a file, not a folder; choose another path")
    out.parent.mkdir(parents=True, exist_ok=True)
    save_array_atomic(out, array)
    print(f"wrote {out} {tuple(array.shape)}")

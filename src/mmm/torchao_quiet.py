"""Importing torchao without its import-time noise.

torchao is installed for the int8 quantizer (mmm.generation.precision), and transformers imports
it by itself when it loads any model (its quantization integrations). On a CPU build each import
logs: a failed load of each compiled CUDA extension (mxfp8, cutlass), "Detected no triton", and
two torch deprecation lines for its enums. None of it concerns what this package uses: the CUDA
extensions are skipped (TORCHAO_FORCE_SKIP_LOADING_SO_FILES, unless the caller set it) and the
first import runs with those loggers at ERROR.
"""

from __future__ import annotations

import logging
import os
import sys
from contextlib import contextmanager

NOISY_LOGGERS = ("torchao", "torch.utils._pytree")


@contextmanager
def quiet_torchao_import():
    """Run the block (an import of torchao, or a transformers model load) without torchao's
    import-time warnings. Once torchao is imported it does nothing: there is nothing left to hide."""
    if "torchao" in sys.modules:
        yield
        return
    os.environ.setdefault("TORCHAO_FORCE_SKIP_LOADING_SO_FILES", "1")
    loggers = [logging.getLogger(name) for name in NOISY_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)

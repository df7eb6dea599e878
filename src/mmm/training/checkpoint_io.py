"""Checkpoint saves that are atomic on every file system.

Lightning's own TorchCheckpointIO saves through an fsspec transaction, which for a local path
writes the file under $TMPDIR and then moves it: across file systems (a tmpfs /tmp, a cluster's
node-local /tmp and a shared /scratch) that move is a copy into the real name, so a kill during
it leaves a truncated `last.ckpt`, and nothing is fsynced. `AtomicCheckpointIO` writes into a
temporary file in the checkpoint's own folder, fsyncs it, renames it over the real name and
fsyncs the folder: `last.ckpt` is the previous complete checkpoint until the new one is complete.

Only global rank 0 saves under DDP (the strategy calls the plugin on rank 0 only), so one
process writes each file. Paths with a URL scheme (s3://, gs://) go through Lightning's save.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.plugins import TorchCheckpointIO
from lightning.fabric.utilities.cloud_io import _is_local_file_protocol

from mmm.atomic import atomic_write, remove_stale_temporaries

# Test hook: seconds to wait after the temporary file is complete and before the rename, so a
# test can kill the training while a save is in progress (unset in normal use).
SAVE_DELAY_ENV = "MMM_TEST_CHECKPOINT_SAVE_DELAY"


class AtomicCheckpointIO(TorchCheckpointIO):
    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None or not _is_local_file_protocol(path):
            return super().save_checkpoint(checkpoint, path, storage_options=storage_options)
        path = Path(path)
        remove_stale_temporaries(path)  # what an earlier, killed save of this file left
        with atomic_write(path, "wb") as fh:
            torch.save(checkpoint, fh)
            delay = os.environ.get(SAVE_DELAY_ENV)
            if delay:
                fh.flush()
                time.sleep(float(delay))

"""Content fingerprints: which model weights and which dataset a result was made from.

They key caches (tokens of a dataset under a tokenizer) and tag runs and registered models, so
a different tokenizer or changed data never reuses stale results.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch


def tensors_fingerprint(state: dict[str, torch.Tensor], prefix: str = "") -> str:
    """Short sha256 over the names, shapes, dtypes and bytes of the tensors whose name starts
    with `prefix` (sorted by name)."""
    h = hashlib.sha256()
    for name in sorted(k for k in state if k.startswith(prefix)):
        t = state[name]
        if not isinstance(t, torch.Tensor):
            continue
        t = t.detach().cpu().contiguous().reshape(-1)  # 0-d tensors cannot be viewed as bytes
        h.update(f"{name}:{tuple(state[name].shape)}:{t.dtype}".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()[:16]


_DATA_PARTS = ("new_joint_vecs", "texts")
_SPLITS = ("train.txt", "val.txt", "test.txt", "Mean.npy", "Std.npy")


def dataset_fingerprint(root: str | Path, extra_parts: tuple[str, ...] = ()) -> str:
    """Short sha256 over the content of a dataset's features, captions, splits and statistics,
    and of the folders `extra_parts` names (e.g. labels, new_joints) where they exist.

    File hashes are remembered in <root>/.fingerprint-cache.json by (size, mtime, ctime, inode),
    so a second call only reads what changed: a rewrite that keeps the size and sets the mtime
    back still changes the ctime (which no user call can set), and a file replaced by rename
    has another inode.
    """
    root = Path(root)
    cache_path = root / ".fingerprint-cache.json"
    try:
        cache = json.loads(cache_path.read_text())
    except (OSError, ValueError):
        cache = {}
    # (relative name, path) in the fingerprint's order: the split files, then each folder's
    # entries sorted by name. os.scandir and plain strings: 60k files in a fraction of a second.
    files = [(name, str(root / name)) for name in _SPLITS if (root / name).exists()]
    for part in (*_DATA_PARTS, *extra_parts):
        if (root / part).is_dir():
            with os.scandir(root / part) as entries:
                names = sorted((entry.name, entry.path) for entry in entries)
            files += [(f"{part}/{name}", path) for name, path in names]
    total = hashlib.sha256()
    fresh = {}
    for rel, path in files:
        st = os.stat(path)
        key = f"{st.st_size}:{st.st_mtime_ns}:{st.st_ctime_ns}:{st.st_ino}"
        digest = cache.get(rel, {}).get(key) if isinstance(cache.get(rel), dict) else None
        if digest is None:
            digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        fresh[rel] = {key: digest}
        total.update(f"{rel}:{digest}\n".encode())
    if fresh != cache:
        try:
            tmp = cache_path.with_name(f".fingerprint-cache.json.tmp-{os.getpid()}")
            tmp.write_text(json.dumps(fresh))
            os.replace(tmp, cache_path)
        except OSError:
            pass  # a read-only dataset is fine: the fingerprint is just recomputed next time
    return total.hexdigest()[:16]

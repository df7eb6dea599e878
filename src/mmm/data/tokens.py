"""Motion tokens of a dataset under one tokenizer, computed once and cached on disk.

<cache_dir>/<tokenizer identity>[-<encoding>]-<data fingerprint>/tokens.npz and meta.json (the
encoding, e.g. `search4x1`, named unless it is the nearest code: mmm.tokenizer.search): every motion's
(T // 4,) codes, or (T // 4, 2) [lower, upper] codes of a part-aware tokenizer, concatenated into
one `codes` array with `offsets` (motions + 1,); meta.json lists the motion ids in that order
(`"format": 2`). One array instead of one archive entry per motion: 30k motions open in a
fraction of a second instead of seconds. Caches of the first format (an entry per motion id, no
`format` in meta.json) are still read. The folder name carries both fingerprints, so another
tokenizer or changed data can never reuse stale tokens. A caption with a #start#end span selects
codes [start // 4, end // 4).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from mmm.data.arrays import load_arrays
from mmm.data.humanml3d import DataError, FeatureStore, read_split

log = logging.getLogger(__name__)

TOKEN_CACHE_FORMAT = 2


class TokenCache:
    """Read-only view of cached tokens: cache[motion_id] -> (L,) int64 codes."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        try:
            self.meta = json.loads((self.folder / "meta.json").read_text())
        except (OSError, ValueError) as e:
            raise DataError(
                self.folder / "meta.json", f"unreadable token cache description ({e})", self._rebuild_hint()
            ) from None
        self._tokens: dict[str, np.ndarray] | None = None

    def _rebuild_hint(self) -> str:
        return (
            f"delete the folder {self.folder}: the next `mmm tokenize` (or stage-2 training) writes it again"
        )

    def _load(self) -> dict[str, np.ndarray]:
        if self._tokens is None:
            path = self.folder / "tokens.npz"
            arrays = load_arrays(path, "token cache", self._rebuild_hint())
            if self.meta.get("format") != TOKEN_CACHE_FORMAT:
                self._tokens = {k: v.astype(np.int64) for k, v in arrays.items()}
                return self._tokens
            try:
                ids, codes, offsets = self.meta["ids"], arrays["codes"].astype(np.int64), arrays["offsets"]
                if len(offsets) != len(ids) + 1 or offsets[-1] != len(codes) or np.any(np.diff(offsets) < 0):
                    raise ValueError(f"{len(ids)} ids, {len(offsets)} offsets, {len(codes)} codes")
            except (KeyError, ValueError) as e:
                raise DataError(path, f"inconsistent token cache ({e})", self._rebuild_hint()) from None
            self._tokens = {m: codes[offsets[i] : offsets[i + 1]] for i, m in enumerate(ids)}
        return self._tokens

    def __getitem__(self, motion_id: str) -> np.ndarray:
        tokens = self._load()
        if motion_id not in tokens:
            raise KeyError(
                f"{motion_id}: no tokens in {self.folder} (the cache covers the ids of "
                f"{', '.join(self.meta['splits'])})"
            )
        return tokens[motion_id]

    def __contains__(self, motion_id: str) -> bool:
        return motion_id in self._load()

    def __len__(self) -> int:
        return len(self._load())

    def __getstate__(self):
        return {"folder": self.folder, "meta": self.meta, "_tokens": None}


def token_cache_folder(
    cache_dir: str | Path, tokenizer_identity: str, data_fingerprint: str, encoding: str = "nearest"
) -> Path:
    """The cache of one (tokenizer, dataset content, encoding): `encoding` is the tokenizer's
    `encode_cfg.label`, so tokens of the code search never mix with nearest-code ones."""
    key = tokenizer_identity if encoding == "nearest" else f"{tokenizer_identity}-{encoding}"
    return Path(cache_dir) / f"{key}-{data_fingerprint}"


@torch.no_grad()
def tokenize_dataset(
    tokenizer,
    root: str | Path,
    folder: str | Path,
    *,
    splits: tuple[str, ...] = ("train", "val", "test"),
    batch_size: int = 64,
    device: str | torch.device = "cpu",
    meta: dict | None = None,
    progress: bool = True,
    encoding=None,
) -> TokenCache:
    """Encode every motion of `splits` with `tokenizer` (a TokenizerModule: its own mean/std
    normalize the features) as `encoding` says (a CodeSearchConfig; None: the tokenizer's own
    `encode_cfg`) and write the cache atomically; returns it (reused if present)."""
    folder = Path(folder)
    if (folder / "meta.json").exists() and (folder / "tokens.npz").exists():
        return TokenCache(folder)
    root = Path(root)
    feature_dim = tokenizer.tokenizer.feature_dim
    down = tokenizer.tokenizer.cfg.downsample
    ids = sorted({i for split in splits if (root / f"{split}.txt").exists() for i in read_split(root, split)})
    by_length: dict[int, list[tuple[str, np.ndarray]]] = defaultdict(list)
    too_short = []
    store = FeatureStore(root, feature_dim)
    for motion_id in ids:
        features = store.load(motion_id)
        usable = features.shape[0] // down * down
        if usable == 0:
            too_short.append(motion_id)
            continue
        by_length[usable].append((motion_id, features[:usable]))
    if not by_length:
        raise DataError(
            root, f"no motion of {', '.join(splits)} is at least {down} frames long", "check the dataset"
        )
    tokenizer = tokenizer.to(device).eval()
    num_codes = max(q.num_codes for q in tokenizer.tokenizer.quantizers.values())
    mean, std = tokenizer.mean.cpu().numpy(), tokenizer.std.cpu().numpy()
    tokens: dict[str, np.ndarray] = {}
    bar = tqdm(
        total=sum(len(v) for v in by_length.values()),
        desc="tokenizing motions",
        unit="motion",
        disable=not progress,
    )
    # Same-length batches: padding would leak into the last codes through the convolutions.
    for length, group in sorted(by_length.items()):
        for start in range(0, len(group), batch_size):
            chunk = group[start : start + batch_size]
            x = torch.from_numpy(np.stack([(f - mean) / std for _, f in chunk]).astype(np.float32)).to(device)
            codes = tokenizer.encode(x, encoding).cpu().numpy()
            for (motion_id, _), c in zip(chunk, codes):
                tokens[motion_id] = c.astype(np.int16 if num_codes <= 32767 else np.int32)
            bar.update(len(chunk))
    bar.close()
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.with_name(f".{folder.name}.tmp-{os.getpid()}")
    tmp.mkdir(parents=True, exist_ok=True)
    order = sorted(tokens)
    offsets = np.cumsum([0] + [len(tokens[m]) for m in order], dtype=np.int64)
    np.savez(tmp / "tokens.npz", codes=np.concatenate([tokens[m] for m in order]), offsets=offsets)
    info = dict(meta or {})
    info.update(
        {
            "format": TOKEN_CACHE_FORMAT,
            "splits": list(splits),
            "motions": len(tokens),
            "left_out_too_short": too_short,
            "num_codes": num_codes,
            "downsample": down,
            "encoding": (encoding or tokenizer.encode_cfg).label,
        }
    )
    info["ids"] = order  # last: the file stays readable above it
    (tmp / "meta.json").write_text(json.dumps(info, indent=2))
    try:
        os.replace(tmp, folder)  # fails when the folder exists (a directory is not replaced by another)
    except OSError:
        if not ((folder / "meta.json").exists() and (folder / "tokens.npz").exists()):
            raise

        shutil.rmtree(tmp)  # another process finished first: keep its identical result
    if too_short:
        log.warning(
            "tokenizing %s: left out %d motions shorter than %d frames (e.g. %s)",
            root,
            len(too_short),
            down,
            ", ".join(too_short[:3]),
        )
    return TokenCache(folder)

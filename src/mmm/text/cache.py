"""Caption embeddings cached on disk, so training never runs the text encoder per step.

Layout of cache_dir/<sanitized encoder identity>/ (generation g increases with every build):
    meta.json                 identity, dims, count, generation, truncated total (the commit point)
    index.<g>.json            caption -> row
    sentences.<g>.npy         (N, Ds) float32
    words.<g>.npy             (total_tokens, Dw) float16, only the real (mask True) positions
    offsets.<g>.npy           (N + 1,) int64, row i's words are words[offsets[i]:offsets[i + 1]]
    truncated.<g>.npy         (N,) bool, the caption was cut to the encoder's limit
A build writes a new generation under temporary names, renames them into place, and commits by
replacing meta.json last, so readers never see a half-written cache. Format 2 encodes in fixed
shapes, so a caption's embedding does not depend on what else is cached; a format-1 cache (built
before) is re-embedded whole by its next build, each caption keeping its row. Arrays are opened memory-
mapped on first use; a pickled cache (DataLoader workers) reopens its files in each process.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Iterable

import numpy as np
import torch
from tqdm.auto import tqdm

from mmm.atomic import atomic_write, file_lock
from mmm.data.arrays import load_array

from .base import TextEmbedding, TextEncoder

log = logging.getLogger(__name__)

FORMAT_VERSION = 2
# Format 1: the same files, but a caption's embedding could depend on the captions encoded with it
# (mixed padded batches before the fixed-shape passes; their first versions still wrote format 1).
_REEMBEDDED_FORMATS = (1,)
_ARRAYS = ("sentences", "words", "offsets", "truncated")


def sanitize_identity(identity: str) -> str:
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", identity).strip("._")
    if not safe:
        raise ValueError(f"encoder identity {identity!r} gives no usable folder name")
    return safe


def _locked(folder: Path):
    """An exclusive lock on the folder while building (several ranks may build at once)."""
    return file_lock(folder / ".lock")


def _write_json_atomic(path: Path, obj) -> None:
    with atomic_write(path, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, ensure_ascii=False)


class CaptionEmbeddingCache:
    """Sentence and word embeddings of captions for one text encoder identity."""

    def __init__(self, cache_dir: str | Path, encoder_identity: str):
        self.cache_dir = Path(cache_dir)
        self.encoder_identity = encoder_identity
        self.folder = self.cache_dir / sanitize_identity(encoder_identity)
        self._reset()
        self._load_meta()

    # ---------------------------------------------------------------- state and pickling

    def _reset(self) -> None:
        self._meta: dict | None = None
        self._index: dict[str, int] | None = None
        self._arrays: dict[str, np.ndarray] = {}

    def __getstate__(self):
        return {"cache_dir": self.cache_dir, "encoder_identity": self.encoder_identity, "folder": self.folder}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._reset()

    def _load_meta(self) -> dict | None:
        """Read meta.json (None while the cache is empty); refuse another encoder's cache."""
        path = self.folder / "meta.json"
        if not path.is_file():
            self._meta = None
            return None
        meta = json.loads(path.read_text(encoding="utf-8"))
        if meta.get("identity") != self.encoder_identity:
            raise ValueError(
                f"the caption cache in {self.folder} was built by text encoder {meta.get('identity')!r}, "
                f"not {self.encoder_identity!r}; use another cache_dir or delete that folder"
            )
        if meta.get("format") not in (FORMAT_VERSION, *_REEMBEDDED_FORMATS):
            raise ValueError(
                f"the caption cache in {self.folder} has format {meta.get('format')!r}, this package "
                f"reads format {FORMAT_VERSION}; delete that folder: it is rebuilt on the next use"
            )
        if self._meta is None or meta["generation"] != self._meta["generation"]:
            self._index = None
            self._arrays = {}
        self._meta = meta
        return meta

    def _file(self, kind: str, generation: int) -> Path:
        return self.folder / (f"index.{generation}.json" if kind == "index" else f"{kind}.{generation}.npy")

    @property
    def index(self) -> dict[str, int]:
        if self._index is None:
            if self._meta is None:
                return {}
            path = self._file("index", self._meta["generation"])
            self._index = json.loads(path.read_text(encoding="utf-8"))
        return self._index

    def _array(self, kind: str) -> np.ndarray:
        arr = self._arrays.get(kind)
        if arr is None:
            try:
                arr = self._open(kind)
            except FileNotFoundError:
                # Another process built a newer generation and removed this one. Rows only ever
                # get appended, so row numbers from the older index stay valid in the new arrays.
                self._load_meta()
                arr = self._open(kind)
            self._arrays[kind] = arr
        return arr

    def _open(self, kind: str) -> np.ndarray:
        """The memory-mapped array file of the current generation; a damaged one a ValueError naming it."""
        path = self._file(kind, self._meta["generation"])
        if not path.exists():
            raise FileNotFoundError(path)

        return load_array(
            path,
            "caption embedding cache",
            f"delete the folder {self.folder}: it is rebuilt on the next use",
            mmap_mode="r",
        )

    def __contains__(self, caption) -> bool:
        return caption in self.index

    def __len__(self) -> int:
        return len(self.index)

    @property
    def truncated_total(self) -> int:
        return int(self._meta["truncated"]) if self._meta else 0

    # ---------------------------------------------------------------- reading

    def lookup(self, captions: list[str]) -> TextEmbedding:
        """B captions -> TextEmbedding with words padded to the longest caption in the batch.

        sentence (B, Ds) float32, words (B, Lmax, Dw) float32 (zeros at padding), word_mask (B, Lmax).
        """
        if isinstance(captions, str):
            raise TypeError("lookup() takes a list of captions, not a single string")
        captions = list(captions)
        index = self.index
        if any(c not in index for c in captions):
            self._load_meta()  # another process may have extended the cache since it was opened
            index = self.index
        rows = []
        for c in captions:
            row = index.get(c)
            if row is None:
                raise KeyError(
                    f"caption {c!r} is not in the caption cache {self.folder} ({len(index)} captions); "
                    "build it first: CaptionEmbeddingCache(cache_dir, encoder.identity).build(encoder, "
                    "captions)"
                )
            rows.append(row)
        if self._meta is None:  # only reachable with no captions at all
            return TextEmbedding(
                torch.zeros(0, 0), torch.zeros(0, 0, 0), torch.zeros(0, 0, dtype=torch.bool), 0
            )

        sentences = self._array("sentences")
        words, offsets, truncated = self._array("words"), self._array("offsets"), self._array("truncated")
        B, Dw = len(rows), self._meta["word_dim"]
        lengths = [int(offsets[r + 1] - offsets[r]) for r in rows]
        L = max(lengths, default=0)
        out_words = np.zeros((B, L, Dw), dtype=np.float32)
        mask = np.zeros((B, L), dtype=bool)
        for i, (r, n) in enumerate(zip(rows, lengths)):
            out_words[i, :n] = words[offsets[r] : offsets[r] + n]
            mask[i, :n] = True
        sent = np.asarray(sentences[np.asarray(rows, dtype=np.int64)], dtype=np.float32).reshape(B, -1)
        n_truncated = int(np.asarray(truncated[np.asarray(rows, dtype=np.int64)]).sum()) if rows else 0
        return TextEmbedding(
            torch.from_numpy(sent), torch.from_numpy(out_words), torch.from_numpy(mask), n_truncated
        )

    # ---------------------------------------------------------------- writing

    def build(
        self, encoder: TextEncoder, captions: Iterable[str], batch_size: int = 32, progress: bool = True
    ) -> dict:
        """Encode the captions not cached yet and add them; returns {"cached", "added", "truncated",
        "reembedded"}: unique requested captions already present, captions encoded now, how many of
        those were cut to the encoder's limit, and how many cached captions were encoded again (a
        format-1 cache, all of them, each keeping its row). Each encoder pass takes exactly
        `batch_size` captions of one token count, so a caption's embedding does not depend on what
        else is cached."""
        if encoder.identity != self.encoder_identity:
            raise ValueError(
                f"this caption cache belongs to text encoder {self.encoder_identity!r}, "
                f"not {encoder.identity!r}; open CaptionEmbeddingCache(cache_dir, encoder.identity)"
            )
        if isinstance(captions, str):
            raise TypeError("build() takes an iterable of captions, not a single string")
        unique: dict[str, None] = {}
        for i, c in enumerate(captions):
            if not isinstance(c, str) or not c.strip():
                raise ValueError(
                    f"caption #{i} is empty, whitespace only or not a string ({c!r}); it cannot be embedded"
                )
            unique.setdefault(c, None)

        self.folder.mkdir(parents=True, exist_ok=True)
        with _locked(self.folder):
            self._load_meta()
            index = dict(self.index)
            new = [c for c in unique if c not in index]
            counts = {"cached": len(unique) - len(new), "added": len(new), "truncated": 0, "reembedded": 0}
            if self._meta and self._meta["format"] in _REEMBEDDED_FORMATS:
                log.warning(
                    "caption cache %s has format %s, whose embeddings may depend on the captions encoded "
                    "with them; encoding its %d captions again (format %d)",
                    self.folder,
                    self._meta["format"],
                    len(index),
                    FORMAT_VERSION,
                )
                counts["reembedded"] = len(index)
                new, index = sorted(index, key=index.get) + new, {}  # cached rows first, in row order
            if new:
                flags = self._write_generation(encoder, index, new, batch_size, progress)
                counts["truncated"] = int(flags[counts["reembedded"] :].sum())
        return counts

    def _write_generation(self, encoder, index, new, batch_size, progress) -> np.ndarray:
        """Append `new` after the rows of `index` (empty: a whole new cache of `new` alone) as the
        next generation; returns the new captions' truncation flags, in their order."""
        gen = (self._meta["generation"] + 1) if self._meta else 0
        old = self._meta if index else None  # the rows kept from the current generation
        n_old = len(index)
        Ds, Dw = encoder.sentence_dim, encoder.word_dim
        if old and (old["sentence_dim"], old["word_dim"]) != (Ds, Dw):
            raise ValueError(
                f"caption cache {self.folder} holds dims {old['sentence_dim']}/{old['word_dim']}, encoder "
                f"gives {Ds}/{Dw}"
            )
        # A caption's embedding must not depend on the captions cached with it. Padded to a batch's
        # longest caption, or in a batch of another size, the same caption's float32 embedding moves
        # by about 1e-7 (1e-6 in the word features), and a model trained on the cache then learns
        # something else (an evaluator's test R-Precision top-1 0.709 against 0.734; README, "Stage
        # 2"). So every pass encodes `batch_size` captions of one token count, the last batch of a
        # count filled with repeats of its first caption: the same shapes whatever else is added.
        # The rows are stored in the order of `new`, whatever the order of the passes.
        counted = encoder.count_tokens(new)
        tokens = [min(n, encoder.max_words) for n in counted]
        flags = np.asarray([n > encoder.max_words for n in counted], dtype=bool)
        order = sorted(range(len(new)), key=lambda i: (tokens[i], new[i]))  # the passes' order
        starts, run = [], 0  # where each pass begins: a new token count, or batch_size more of one
        for k, i in enumerate(order):
            run = run + 1 if k and tokens[i] == tokens[order[k - 1]] else 0
            if run % batch_size == 0:
                starts.append(k)
        tmp_dir = Path(tempfile.mkdtemp(dir=self.folder, prefix=".build-"))
        try:
            sentences = np.empty((len(new), Ds), dtype=np.float32)
            lengths = np.empty(len(new), dtype=np.int64)
            raw_words = tmp_dir / "words.raw"  # the real positions in the passes' order
            batches = zip(starts, starts[1:] + [len(new)])
            if progress:
                batches = tqdm(
                    batches, total=len(starts), desc=f"caption embeddings ({encoder.name})", unit="batch"
                )
            with open(raw_words, "wb") as fh:
                for start, stop in batches:
                    rows = order[start:stop]
                    chunk = [new[i] for i in rows]
                    emb = encoder.encode(chunk + chunk[:1] * (batch_size - len(chunk)))
                    mask = emb.word_mask.cpu()[: len(chunk)]
                    sentences[rows] = emb.sentence[: len(chunk)].float().cpu().numpy()
                    n_real = mask.sum(1)
                    if not torch.equal(mask, torch.arange(mask.shape[1]) < n_real.unsqueeze(1)):
                        raise ValueError(
                            f"{encoder.name}: word_mask is not a prefix mask; the cache stores rows as "
                            "prefixes"
                        )
                    lengths[rows] = n_real.numpy()
                    # One boolean index for the batch: the real positions, row after row. (Indexing
                    # row by row costs milliseconds per call on CPU.)
                    words = emb.words[: len(chunk)].float().cpu()[mask]
                    fh.write(words.numpy().astype(np.float16).tobytes())

            old_tokens = int(self._array("offsets")[-1]) if old else 0
            total_tokens = old_tokens + int(lengths.sum())
            open_memmap = np.lib.format.open_memmap
            words_out = open_memmap(
                tmp_dir / "words.npy", mode="w+", dtype=np.float16, shape=(total_tokens, Dw)
            )
            step = 1 << 16
            if old:
                old_words = self._array("words")
                for s in range(0, old_tokens, step):
                    e = min(s + step, old_tokens)
                    words_out[s:e] = old_words[s:e]
            new_offsets = old_tokens + np.concatenate([[0], np.cumsum(lengths)])
            raw = np.memmap(raw_words, dtype=np.float16, mode="r", shape=(int(lengths.sum()), Dw))
            pos = 0
            for i in order:
                n = int(lengths[i])
                words_out[new_offsets[i] : new_offsets[i] + n] = raw[pos : pos + n]
                pos += n
            assert pos == len(raw)
            del raw
            words_out.flush()
            del words_out
            raw_words.unlink()

            if old:
                all_sent = np.concatenate([np.asarray(self._array("sentences")), sentences])
                all_offsets = np.concatenate([np.asarray(self._array("offsets")), new_offsets[1:]])
                all_flags = np.concatenate([np.asarray(self._array("truncated")), flags])
            else:
                all_sent, all_offsets, all_flags = sentences, new_offsets, flags
            np.save(tmp_dir / "sentences.npy", all_sent.astype(np.float32))
            np.save(tmp_dir / "offsets.npy", all_offsets.astype(np.int64))
            np.save(tmp_dir / "truncated.npy", all_flags)
            index = dict(index)
            for k, c in enumerate(new):
                index[c] = n_old + k
            (tmp_dir / "index.json").write_text(json.dumps(index, ensure_ascii=False), encoding="utf-8")

            for kind in _ARRAYS:
                os.replace(tmp_dir / f"{kind}.npy", self._file(kind, gen))
            os.replace(tmp_dir / "index.json", self._file("index", gen))
            meta = {
                "format": FORMAT_VERSION,
                "identity": self.encoder_identity,
                "encoder": encoder.name,
                "generation": gen,
                "count": len(index),
                "sentence_dim": Ds,
                "word_dim": Dw,
                "max_words": encoder.max_words,
                "total_tokens": total_tokens,
                "truncated": (old["truncated"] if old else 0) + int(flags.sum()),
            }
            _write_json_atomic(self.folder / "meta.json", meta)  # the commit point
        finally:
            shutil.rmtree(tmp_dir, ignore_errors=True)

        self._arrays = {}
        self._index = None
        self._load_meta()
        if gen:  # the previous generation; open memory maps elsewhere keep their data on POSIX
            for kind in _ARRAYS:
                self._file(kind, gen - 1).unlink(missing_ok=True)
            self._file("index", gen - 1).unlink(missing_ok=True)
        return flags

"""Torch datasets over loaded motions: random windows for the tokenizer, captioned motions for stage 2."""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from mmm.data.humanml3d import MotionItem


def normalize(features: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    return ((features - mean) / std).astype(np.float32, copy=False)


class MotionWindowDataset(Dataset):
    """Every window of `window` frames of every motion, normalized: items are (window, D) tensors.

    Indexing enumerates all window positions, so a uniform sampler draws motions in proportion to
    their number of windows (the reference's length-weighted sampling) with no randomness inside
    the dataset: reproducible, and a DistributedSampler splits it cleanly across ranks.

    Windows are normalized when drawn (the same numbers as normalizing whole motions first), so the
    motions stay as loaded: views of the memory-mapped feature pack, not a second copy in memory.

    start_windows: the share of the indices that, once `at_start` is switched on (the decoder
    refinement does it), are a clip's first `window` frames (each clip equally often); before, they
    are windows anywhere like the rest, so the codebook trains on the usual windows. A clip's first
    frame is unlike the others: its heading is the identity, so the yaw velocity of frame 0
    carries the turn to the smoothed heading of frame 1 (up to 0.1 rad) and rotates the whole
    recovered root path. Random windows begin there once in (length - window + 1) draws, so the
    decoder hardly learns it, while every decoded clip (a reconstruction, a generated motion)
    begins there. The switch lives in shared memory, so loader workers see it too.
    """

    def __init__(
        self,
        motions: list[np.ndarray],
        mean: np.ndarray,
        std: np.ndarray,
        window: int = 64,
        start_windows: float = 0.0,
    ):
        if not 0.0 <= start_windows < 1.0:
            raise ValueError(
                f"refine.start_windows={start_windows}: it is the share of the refinement's windows that "
                "begin at a clip's first frame; use a value in [0, 1)"
            )
        self.window = window
        self.mean, self.std = mean, std
        self.motions = [m for m in motions if m.shape[0] >= window]
        self.num_too_short = len(motions) - len(self.motions)
        if not self.motions:
            raise ValueError(f"no motion is at least {window} frames long (the tokenizer's window)")
        counts = [m.shape[0] - window + 1 for m in self.motions]
        self.starts = np.concatenate(([0], np.cumsum(counts)))
        self.num_anywhere = int(self.starts[-1])
        self.num_at_start = round(self.num_anywhere * start_windows / (1.0 - start_windows))
        self._at_start = torch.zeros((), dtype=torch.bool).share_memory_()

    @property
    def at_start(self) -> bool:
        """Whether the last `num_at_start` indices are clip starts (else windows anywhere)."""
        return bool(self._at_start)

    @at_start.setter
    def at_start(self, value: bool) -> None:
        self._at_start.fill_(bool(value))

    def __len__(self) -> int:
        return self.num_anywhere + self.num_at_start

    def _window(self, index: int) -> np.ndarray:
        """The raw frames (window, D) of window `index`: a view of its motion."""
        index %= len(self)  # samplers may tag indices with the epoch
        if index >= self.num_anywhere and self.at_start:
            k, offset = (index - self.num_anywhere) % len(self.motions), 0
        else:
            if index >= self.num_anywhere:  # a fixed window anywhere, spread by a multiplicative hash
                index = index * 2654435761 % self.num_anywhere
            k = int(np.searchsorted(self.starts, index, side="right")) - 1
            offset = index - int(self.starts[k])
        return self.motions[k][offset : offset + self.window]

    def __getitem__(self, index: int) -> torch.Tensor:
        return torch.from_numpy(normalize(self._window(index), self.mean, self.std))

    def __getitems__(self, indices: list[int]) -> list[torch.Tensor]:
        """A loader's batch: the windows normalized in one operation, the same numbers as one by
        one (elementwise), with a fraction of the per-window overhead."""
        windows = normalize(np.stack([self._window(i) for i in indices]), self.mean, self.std)
        return list(torch.from_numpy(windows))


class TextMotionDataset(Dataset):
    """Captioned motions for stage 2: {"caption", "motion" (T, D) normalized, "length", "name"}.

    As the reference does: a random caption of the item, the length cut to a multiple of
    `unit_length` (one unit shorter with probability 1/3), at most `max_length`, at a random
    offset. Sample `index` draws from a generator seeded by (seed, index) (see TokenTextDataset).
    """

    def __init__(
        self,
        items: list[MotionItem],
        mean: np.ndarray,
        std: np.ndarray,
        *,
        max_length: int = 196,
        unit_length: int = 4,
        random_crop: bool = True,
        seed: int = 0,
    ):
        self.items = items
        self.mean, self.std = mean, std
        self.max_length, self.unit_length, self.random_crop, self.seed = (
            max_length,
            unit_length,
            random_crop,
            seed,
        )

    def __len__(self) -> int:
        return len(self.items)

    def crop_length(self, length: int, shorter: bool) -> int:
        units = min(length, self.max_length) // self.unit_length - (1 if shorter else 0)
        return max(units, 1) * self.unit_length

    def __getitem__(self, index: int) -> dict:
        item = self.items[index % len(self.items)]
        if self.random_crop:
            rng = np.random.default_rng((self.seed, index))
            caption = item.captions[int(rng.integers(len(item.captions)))].text
            length = self.crop_length(item.length, shorter=bool(rng.random() < 1 / 3))
            offset = int(rng.integers(item.length - length + 1))
        else:
            caption = item.captions[0].text
            length, offset = self.crop_length(item.length, shorter=False), 0
        motion = normalize(item.features[offset : offset + length], self.mean, self.std)
        return {"caption": caption, "motion": torch.from_numpy(motion), "length": length, "name": item.name}


class MotionClipDataset(Dataset):
    """Whole clips for validation: {"motion" (T, D) normalized, "length", "name"}, T cut to a
    multiple of `unit_length` and at most `max_length` frames from the start."""

    def __init__(
        self,
        clips: dict[str, np.ndarray],
        mean: np.ndarray,
        std: np.ndarray,
        *,
        max_length: int = 196,
        unit_length: int = 4,
    ):
        self.names = sorted(clips)
        self.clips, self.mean, self.std = clips, mean, std
        self.max_length, self.unit_length = max_length, unit_length

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: int) -> dict:
        name = self.names[index % len(self.names)]
        clip = self.clips[name]
        length = min(clip.shape[0], self.max_length) // self.unit_length * self.unit_length
        return {
            "motion": torch.from_numpy(normalize(clip[:length], self.mean, self.std)),
            "length": length,
            "name": name,
        }


def collate_motions(batch: list[dict]) -> dict:
    """Pad motions to the longest in the batch: motion (B, T, D), lengths (B,), and the other
    keys (caption, name) as lists under their plural names."""
    lengths = torch.tensor([b["length"] for b in batch], dtype=torch.long)
    dim = batch[0]["motion"].shape[-1]
    motion = torch.zeros(len(batch), int(lengths.max()), dim)
    for i, b in enumerate(batch):
        motion[i, : b["length"]] = b["motion"]
    out = {"motion": motion, "lengths": lengths}
    for key in batch[0]:
        if key not in ("motion", "length"):
            out[key + "s"] = [b[key] for b in batch]
    return out


collate_text_motion = collate_motions


class TokenTextDataset(Dataset):
    """Stage 2: {"tokens" (L,) int64 codes, "caption", "name"} per captioned item.

    An item's codes are its clip's cached tokens over its span [start // 4, end // 4). As the
    reference does: a random caption of the item and, with probability 1/3, one code dropped at
    the head or the tail. The randomness of sample `index` comes from a generator seeded by
    (seed, index), and ShardedRandomSampler tags indices with the epoch, so draws differ per
    epoch, are the same in any worker, and survive a resume.
    """

    def __init__(
        self,
        items: list[MotionItem],
        tokens,
        *,
        unit_length: int = 4,
        max_codes: int = 49,
        seed: int = 0,
        augment: bool = True,
    ):
        self.items, self.tokens, self.unit_length, self.max_codes, self.seed, self.augment = (
            items,
            tokens,
            unit_length,
            max_codes,
            seed,
            augment,
        )

    def __len__(self) -> int:
        return len(self.items)

    def codes(self, item: MotionItem) -> np.ndarray:
        first = item.start // self.unit_length
        return self.tokens[item.motion_id][first : (item.start + item.length) // self.unit_length][
            : self.max_codes
        ]

    def __getitem__(self, index: int) -> dict:
        item = self.items[index % len(self.items)]
        codes = self.codes(item)
        if self.augment:
            rng = np.random.default_rng((self.seed, index))
            caption = item.captions[int(rng.integers(len(item.captions)))].text
            if len(codes) > 1 and rng.random() < 1 / 3:
                codes = codes[:-1] if rng.random() < 0.5 else codes[1:]
        else:
            caption = item.captions[0].text
        return {
            "tokens": torch.from_numpy(np.ascontiguousarray(codes)),
            "caption": caption,
            "name": item.name,
        }


class TokenBatchCollator:
    """Pads codes to [codes, END, PAD, ...], as long as the batch's longest sequence plus END (at
    most max_tokens), and adds the captions' cached text embeddings:
    {"tokens" (B, M) or (B, M, 2) for part-aware codes, "lengths" (B,), "sentence", "words",
    "word_mask", "captions", "names"}."""

    def __init__(self, caption_cache, num_codes: int, max_tokens: int = 50):
        self.caption_cache, self.num_codes, self.max_tokens = caption_cache, num_codes, max_tokens

    def __call__(self, batch: list[dict]) -> dict:
        end, pad = self.num_codes, self.num_codes + 1
        lengths = torch.tensor([len(b["tokens"]) for b in batch], dtype=torch.long)
        parts = tuple(
            torch.as_tensor(batch[0]["tokens"]).shape[1:]
        )  # (2,) for a part-aware tokenizer's [lower, upper]
        tokens = torch.full(
            (len(batch), min(int(lengths.max()) + 1, self.max_tokens), *parts), pad, dtype=torch.long
        )
        for i, b in enumerate(batch):
            n = len(b["tokens"])
            tokens[i, :n] = b["tokens"]
            tokens[i, n] = end
        captions = [b["caption"] for b in batch]
        text = self.caption_cache.lookup(captions)
        return {
            "tokens": tokens,
            "lengths": lengths,
            "sentence": text.sentence,
            "words": text.words,
            "word_mask": text.word_mask,
            "captions": captions,
            "names": [b["name"] for b in batch],
        }

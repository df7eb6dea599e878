"""The frozen text encoder interface shared by MiniLM and CLIP (the encoders import this; it imports
neither)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Mapping, Sequence

import torch


@dataclass
class TextEmbedding:
    """What a text encoder gives the motion transformer for a batch of B texts.

    sentence:  (B, Ds) float32, one vector per text.
    words:     (B, Lw, Dw) float32, per-token features, padded along Lw.
    word_mask: (B, Lw) bool, True at real positions (special tokens included as the encoder
               defines them), False at padding.
    truncated: how many of the B texts were cut to the encoder's limit.
    """

    sentence: torch.Tensor
    words: torch.Tensor
    word_mask: torch.Tensor
    truncated: int

    def __len__(self) -> int:
        return self.sentence.shape[0]

    def to(self, device) -> "TextEmbedding":
        return TextEmbedding(
            self.sentence.to(device), self.words.to(device), self.word_mask.to(device), self.truncated
        )


class TextEncoder(torch.nn.Module):
    """A frozen text encoder: parameters never require grad, the module stays in eval mode.

    Subclasses set `name`, `sentence_dim`, `word_dim`, `max_words` and implement `_encode`
    (already validated texts, run under no_grad) and `count_tokens`.
    `identity` is name + a short sha256 of the weights (and of anything else that changes the
    output, such as a tokenizer vocabulary): the key of caption caches and what MLflow records.
    """

    name: str = ""
    sentence_dim: int
    word_dim: int
    max_words: int

    def _freeze(self) -> None:
        for p in self.parameters():
            p.requires_grad_(False)
        super().train(False)

    def train(self, mode: bool = True) -> "TextEncoder":
        # A parent module's .train() must not switch dropout on inside the frozen encoder.
        return super().train(False)

    @property
    def device(self) -> torch.device:
        for p in self.parameters():
            return p.device
        return torch.device("cpu")

    @property
    def identity(self) -> str:
        cached = self.__dict__.get("_identity")
        if cached is None:
            cached = f"{self.name}-{self._weights_digest()[:12]}"
            self.__dict__["_identity"] = cached
        return cached

    def _weights_digest(self) -> str:
        return state_dict_digest(self.state_dict())

    def encode(self, texts: Sequence[str]) -> TextEmbedding:
        """texts: B strings -> TextEmbedding (sentence (B, Ds), words (B, Lw, Dw), word_mask (B, Lw))."""
        texts = check_texts(texts)
        with torch.no_grad():
            return self._encode(texts)

    def _encode(self, texts: list[str]) -> TextEmbedding:  # pragma: no cover - abstract
        raise NotImplementedError

    def count_tokens(self, texts: Sequence[str]) -> list[int]:  # pragma: no cover - abstract
        """Tokens each text needs including special tokens, before truncation to `max_words`."""
        raise NotImplementedError

    def texts_cut(self, texts: Sequence[str]) -> dict[str, dict]:
        """The texts longer than this encoder reads (it keeps the first `max_words` tokens), each
        with {"tokens": its count, "read": max_words}: what a sample's meta.json and a served row
        record as `text_cut`."""
        texts = [t for t in dict.fromkeys(texts) if t]
        return {
            text: {"tokens": n, "read": self.max_words}
            for text, n in zip(texts, self.count_tokens(texts))
            if n > self.max_words
        }

    def extra_repr(self) -> str:
        return (
            f"name={self.name!r}, sentence_dim={self.sentence_dim}, word_dim={self.word_dim}, "
            f"max_words={self.max_words}"
        )


def check_texts(texts: Sequence[str]) -> list[str]:
    """The texts as a list; a bare string, a non-string or an empty/whitespace-only text is refused."""
    if isinstance(texts, (str, bytes)):
        raise TypeError("encode() takes a list of texts, not a single string; wrap it: encode([text])")
    texts = list(texts)
    for i, t in enumerate(texts):
        if not isinstance(t, str):
            raise TypeError(f"text #{i} is a {type(t).__name__}, not a str: {t!r}")
        if not t.strip():
            raise ValueError(
                f"text #{i} is empty or whitespace only ({t!r}); every text needs at least one word"
            )
    return texts


def state_dict_digest(tensors: Mapping[str, torch.Tensor], extra: str = "") -> str:
    """sha256 over (name, dtype, shape, bytes) of every tensor in name order, plus `extra`.

    Independent of the file format the weights came from, the device and the process.
    """
    h = hashlib.sha256()
    h.update(extra.encode("utf-8"))
    for key in sorted(tensors):
        t = tensors[key].detach().to("cpu").contiguous()
        h.update(f"|{key}|{str(t.dtype)}|{tuple(t.shape)}|".encode("utf-8"))
        if t.numel():
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()

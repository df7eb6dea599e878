"""Decoding passes through `torch.compile` with static shapes (issue 16, item 3).

A decoding pass sees a different sequence length for every requested length and a different
number of masked positions every pass; compiled as they come, each shape would be a new graph
(and, on a GPU, a new CUDA graph). `CompiledDecoding` wraps a transformer (or its fp32/bf16/int8
inference copy) so that every pass has one of a few shapes:

    sequence  the tokens (B, M) are padded with PAD to the next length bucket (multiples of 4 up
              to 16, then of 8, up to the model's max_tokens: at most 9); PAD keys are masked out
              of every attention, as they are for the padding of a mixed-length batch, so the
              real positions' logits are those of the unpadded pass (to float rounding);
    rows      the rows that run (fewer as the samples of a mixed-length batch finish) are padded
              to the next power of two with copies of the last row, whose results are dropped;
    words     the cached keys/values of the words are padded to a multiple of 16 words, masked out;
    head      evaluated at every position of the bucket (a static shape), then the positions where
              codes are drawn are read from it.

The sampler sees the wrapped model unchanged (`text_context`, `forward_cached` and the ids), so
codes are drawn exactly as without compilation. Compilation happens on the first pass of each
shape (tens of seconds at the paper size on a CPU); `mode="reduce-overhead"` adds CUDA graphs on
a GPU, where a batch-1 pass is launch-bound. `TextToMotion(compiled=True)` (or setting
`.compiled`), `mmm generate|edit|generate-long --compile`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from mmm.transformer.network import TextContext

WORD_BUCKET = 16
# Shapes one compiled pass may take: lengths x row counts (dynamo's default allows 8).
RECOMPILE_LIMIT = 64


def length_buckets(max_tokens: int) -> tuple[int, ...]:
    """Sequence lengths a pass is padded to: multiples of 4 up to 16 (short motions, where padding
    costs most in proportion), then of 8, and max_tokens."""
    steps = [*range(4, 17, 4), *range(24, max_tokens, 8)]
    return tuple(n for n in steps if n < max_tokens) + (max_tokens,)


def default_compile_mode(device: torch.device | str) -> str:
    """CUDA graphs on a GPU (a batch-1 pass is launch-bound there); plain inductor on a CPU."""
    return "reduce-overhead" if torch.device(device).type == "cuda" else "default"


class CompiledDecoding(nn.Module):
    """`model` with `forward_cached` compiled over static shapes (module docstring); every other
    attribute (ids, cfg, text_context, ...) is the wrapped model's."""

    def __init__(self, model: nn.Module, mode: str = "default", backend: str = "inductor"):
        super().__init__()
        self.model = model.eval()
        self.buckets = length_buckets(model.cfg.max_tokens)
        self.mode, self.backend = mode, backend
        options = {"mode": mode} if backend == "inductor" else {}
        self._pass = torch.compile(self._logits, dynamic=False, backend=backend, **options)
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, RECOMPILE_LIMIT)

    def __getattr__(self, name: str):
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self._modules["model"], name)

    def forward(self, *args, **kwargs) -> torch.Tensor:
        """The wrapped model's `forward`, not compiled (the reference and released loops use it)."""
        return self.model(*args, **kwargs)

    def _logits(self, tokens, condition, sentence, word_kv, word_mask, see_text) -> torch.Tensor:
        context = TextContext(sentence, list(word_kv), word_mask, see_text)
        return self.model.forward_cached(tokens, context, condition)

    def bucket(self, length: int) -> int:
        for size in self.buckets:
            if size >= length:
                return size
        raise ValueError(f"sequence of {length} tokens is longer than the model's {self.buckets[-1]}")

    @torch.no_grad()
    def forward_cached(
        self,
        tokens: torch.Tensor,
        context: TextContext,
        condition: torch.Tensor | None = None,
        head_rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """What the wrapped model's `forward_cached` returns: (B, M, K) float32 logits, or (N, K)
        at the flat positions `head_rows` (N,) of B * M."""
        B, M = tokens.shape
        pad = self.bucket(M) - M
        if pad:
            tokens = F.pad(tokens, (0, pad), value=self.model.pad_id)
            if condition is not None:
                condition = F.pad(condition, (0, pad), value=self.model.condition.pad_id)
        words = context.word_mask.shape[1]
        extra = math.ceil(words / WORD_BUCKET) * WORD_BUCKET - words
        word_kv, word_mask = tuple(context.word_kv), context.word_mask
        if extra:
            word_kv = tuple((F.pad(k, (0, 0, 0, extra)), F.pad(v, (0, 0, 0, extra))) for k, v in word_kv)
            word_mask = F.pad(word_mask, (0, extra), value=False)
        inputs = [tokens, condition, context.sentence, word_kv, word_mask, context.see_text]
        rows = 1 << (B - 1).bit_length()
        if rows > B:
            index = torch.arange(rows, device=tokens.device).clamp(max=B - 1)
            inputs = [_rows(x, index) for x in inputs]
        logits = self._pass(*inputs)[:B, :M]
        if head_rows is None:  # a copy: CUDA graphs reuse their output buffer on the next pass
            return logits.clone()
        return logits.reshape(B * M, -1).index_select(0, head_rows)


def _rows(x, index: torch.Tensor):
    """x (or each tensor of nested tuples of them) at the rows `index`; None stays None."""
    if x is None:
        return None
    if isinstance(x, tuple):
        return tuple(_rows(t, index) for t in x)
    return x.index_select(0, index)

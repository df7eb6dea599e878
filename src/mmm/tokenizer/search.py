"""Code search: tokenizing a known motion by what the decoder makes of the codes.

Nearest-code quantization picks, at each position, the code nearest the encoder's latent. Decoded,
such a sequence gets the body right but its root velocities carry a small bias of a few percent,
which integrates along the clip into a root path that ends metres away (README, Stage 1). When
the motion is known (tokenizing a dataset for stage 2, measuring reconstruction, the kept frames
of an edit), the encoder can do better: at each position, left to right, try the `candidates`
codes nearest the latent and keep the one whose decoded clip lies closest to the motion in joint
positions, global (so the root path counts) plus root-aligned (so the body does). The choice of
one code moves the root path of every later frame, which is why the whole clip is scored. Each
position costs one decoder call on `candidates - 1` copies of the batch (the code in place is
one of the candidates, already scored); the decoder is unchanged, so generation, which never
encodes, is unchanged too.

`precision` bf16 runs those decoder calls in bfloat16 autocast (the scores and the choice stay
float32): on the demo tokenizer's test clips 1.31x faster on a CPU with AMX units, 0.85 of the
codes the same as float32's and the round trip's MPJPE the same (README, Stage 1: "Code
search"). `auto` is bf16 where bfloat16 is fast (`has_fast_bf16`), fp32 elsewhere; a checkpoint
written before the setting existed gets fp32, so its codes are those it was measured with.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch

from mmm.device import has_fast_bf16

PRECISIONS = ("fp32", "bf16", "auto")


@dataclass
class CodeSearchConfig:
    candidates: int = 4  # codes tried per position, nearest first; 1: the nearest code, no search
    sweeps: int = 1  # passes over the positions
    precision: str = "fp32"  # the decoder calls' arithmetic: fp32 | bf16 | auto (bf16 where it is fast)

    def __post_init__(self):
        if self.precision not in PRECISIONS:
            raise ValueError(
                f"encode.precision={self.precision!r}: must be one of {', '.join(PRECISIONS)} (auto: bf16 "
                "where this machine has fast bfloat16 kernels, fp32 elsewhere)"
            )
        for name in ("candidates", "sweeps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(
                    f"encode.{name}={value!r}: must be an integer >= 1 (encode.candidates=1: the nearest "
                    "code, as the released tokenizer encodes)"
                )

    def resolved(self) -> CodeSearchConfig:
        """This config with `auto` replaced by what this machine runs: fp32 or bf16."""
        if self.precision != "auto":
            return self
        return replace(self, precision="bf16" if has_fast_bf16() else "fp32")

    @property
    def label(self) -> str:
        """'nearest', or 'search<candidates>x<sweeps>' ('-bf16' appended for bfloat16 decoding): names
        token caches and logged metrics."""
        if self.candidates == 1:
            return "nearest"
        suffix = "-bf16" if self.resolved().precision == "bf16" else ""
        return f"search{self.candidates}x{self.sweeps}{suffix}"


def _joint_error(rec: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per clip (N,): mean over frames of the global plus the root-aligned joint error of
    joints (N, T, J, 3)."""
    global_error = (rec - target).norm(dim=-1).mean(-1)
    aligned = ((rec - rec[..., :1, :]) - (target - target[..., :1, :])).norm(dim=-1).mean(-1)
    return (global_error + aligned).mean(-1)


@torch.no_grad()
def search_codes(
    tokenizer,
    motion: torch.Tensor,
    joints: Callable[[torch.Tensor], torch.Tensor],
    cfg: CodeSearchConfig,
    features: int | None = None,
) -> torch.Tensor:
    """Indices shaped as `tokenizer.encode(motion)` gives them, (B, T') or (B, T', 2) for a
    part-aware tokenizer, of normalized motion (B, T, D) whose clips all have T frames.

    joints: normalized features (N, T, features) -> joint positions (N, T, J, 3).
    features: how many leading features of D the joints read (None: all); the decoder calls make
    only those (README, Stage 1: "Code search": 1.2x, the same codes).
    With cfg.candidates == 1 this is `tokenizer.encode(motion)`.
    """
    if cfg.candidates == 1:
        return tokenizer.encode(motion)
    bf16 = cfg.resolved().precision == "bf16"

    def decode(indices: torch.Tensor) -> torch.Tensor:
        autocast = (
            torch.autocast(motion.device.type, dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()
        )
        with autocast:
            return tokenizer.decode(indices, features)  # the decoder hands back float32

    candidates = tokenizer.candidate_codes(motion, cfg.candidates)
    if not tokenizer.part_aware:
        candidates = candidates.unsqueeze(2)
    batch, positions, parts, k = candidates.shape  # (B, T', P, K): per codebook P, nearest first

    def indices(chosen: torch.Tensor) -> torch.Tensor:
        return chosen if tokenizer.part_aware else chosen[..., 0]

    target = joints(motion[..., :features])
    chosen = candidates[..., 0].clone()
    best = _joint_error(joints(decode(indices(chosen))), target)
    others = k - 1  # the code in place is one of the candidates, and its score is `best` already
    target = target.repeat_interleave(others, 0)
    for _ in range(cfg.sweeps):
        for t in range(positions):
            for p in range(parts):
                options = candidates[:, t, p, :]  # (B, K)
                options = options[options != chosen[:, t, p, None]].view(batch, others)
                trial = chosen.repeat_interleave(others, 0).view(batch, others, positions, parts)
                trial[:, :, t, p] = options
                trial = trial.view(batch * others, positions, parts)
                score = _joint_error(joints(decode(indices(trial))), target).view(batch, others)
                value, pick = score.min(-1)
                better = value < best
                chosen[better, t, p] = options[better, pick[better]]
                best = torch.where(better, value, best)
    return indices(chosen)

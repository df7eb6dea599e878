"""Code search: tokenizing a known motion by what the decoder makes of the codes.

Nearest-code quantization picks, at each position, the code nearest the encoder's latent. Decoded,
such a sequence gets the body right but its root velocities carry a small bias of a few percent,
which integrates along the clip into a root path that ends metres away (README, Stage 1). When
the motion is known (tokenizing a dataset for stage 2, measuring reconstruction, the kept frames
of an edit), the encoder can do better: at each position, left to right, try the `candidates`
codes nearest the latent and keep the one whose decoded clip lies closest to the motion in joint
positions, global (so the root path counts) plus root-aligned (so the body does). The choice of
one code moves the root path of every later frame, which is why the whole clip is scored. Each
position costs one decoder call on `candidates` copies of the batch; the decoder is unchanged,
so generation, which never encodes, is unchanged too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch


@dataclass
class CodeSearchConfig:
    candidates: int = 4  # codes tried per position, nearest first; 1: the nearest code, no search
    sweeps: int = 1  # passes over the positions

    def __post_init__(self):
        for name in ("candidates", "sweeps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(
                    f"encode.{name}={value!r}: must be an integer >= 1 (encode.candidates=1: the nearest "
                    "code, as the released tokenizer encodes)"
                )

    @property
    def label(self) -> str:
        """'nearest', or 'search<candidates>x<sweeps>': names token caches and logged metrics."""
        return "nearest" if self.candidates == 1 else f"search{self.candidates}x{self.sweeps}"


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
) -> torch.Tensor:
    """Indices shaped as `tokenizer.encode(motion)` gives them, (B, T') or (B, T', 2) for a
    part-aware tokenizer, of normalized motion (B, T, D) whose clips all have T frames.

    joints: normalized features (N, T, D) -> joint positions (N, T, J, 3).
    With cfg.candidates == 1 this is `tokenizer.encode(motion)`.
    """
    if cfg.candidates == 1:
        return tokenizer.encode(motion)
    candidates = tokenizer.candidate_codes(motion, cfg.candidates)
    if not tokenizer.part_aware:
        candidates = candidates.unsqueeze(2)
    batch, positions, parts, k = candidates.shape  # (B, T', P, K): per codebook P, nearest first

    def indices(chosen: torch.Tensor) -> torch.Tensor:
        return chosen if tokenizer.part_aware else chosen[..., 0]

    target = joints(motion)
    chosen = candidates[..., 0].clone()
    best = _joint_error(joints(tokenizer.decode(indices(chosen))), target)
    target = target.repeat_interleave(k, 0)
    for _ in range(cfg.sweeps):
        for t in range(positions):
            for p in range(parts):
                trial = chosen.repeat_interleave(k, 0).view(batch, k, positions, parts)
                trial[:, :, t, p] = candidates[:, t, p, :]
                trial = trial.view(batch * k, positions, parts)
                score = _joint_error(joints(tokenizer.decode(indices(trial))), target).view(batch, k)
                value, pick = score.min(-1)
                better = value < best
                chosen[better, t, p] = candidates[better, t, p, pick[better]]
                best = torch.where(better, value, best)
    return indices(chosen)

"""The part-aware tokenizer (method.md, upper-body editing): lower and upper body tokenized apart.

Motion (B, T, 263) is split into the lower body (B, T, 107) and the upper body (B, T, 156)
(mmm.motion.parts); each goes through its own MotionTokenizer with its own codebook, so every
time step has one token per part: indices (B, T', 2), [..., 0] lower and [..., 1] upper. Both
tokenizers have the same sizes (one TokenizerConfig). Decoding any lower codes with any upper
codes gives a whole body, which is what editing one part while keeping the other needs.
"""

from __future__ import annotations

import torch
from torch import nn

from mmm.motion.features import FeatureLayout
from mmm.motion.parts import merge_parts, part_indices, split_parts
from mmm.tokenizer.network import MotionTokenizer, TokenizerConfig, TokenizerOutput
from mmm.tokenizer.quantizer import EMAQuantizer

PARTS = ("lower", "upper")  # order of the last axis of the indices


class PartAwareTokenizer(nn.Module):
    """Normalized motion features (B, T, 263) <-> code index pairs (B, T / 4, 2)."""

    # Callers tell the kinds apart by this, not by cfg.part_aware: the two inner tokenizers share the cfg.
    part_aware = True

    def __init__(self, feature_dim: int, cfg: TokenizerConfig):
        super().__init__()
        expected = FeatureLayout(22).dim
        if feature_dim != expected:
            raise ValueError(
                f"a part-aware tokenizer reads the {expected}-d HumanML3D features, got "
                f"feature_dim={feature_dim}; "
                "set model.tokenizer.part_aware=false for other data (KIT-ML)"
            )
        lower_idx, upper_idx = part_indices()
        self.feature_dim, self.cfg = feature_dim, cfg
        self.lower = MotionTokenizer(len(lower_idx), cfg)
        self.upper = MotionTokenizer(len(upper_idx), cfg)

    def forward(self, motion: torch.Tensor) -> TokenizerOutput:
        """Reconstruction (B, T, 263) merged from both parts, indices (B, T', 2), the summed
        commitment loss, the mean perplexity and each codebook's in `perplexities`."""
        lower, upper = split_parts(motion)
        out_lower, out_upper = self.lower(lower), self.upper(upper)
        return TokenizerOutput(
            reconstruction=merge_parts(out_lower.reconstruction, out_upper.reconstruction),
            indices=torch.stack((out_lower.indices, out_upper.indices), dim=-1),
            commit_loss=out_lower.commit_loss + out_upper.commit_loss,
            perplexity=(out_lower.perplexity + out_upper.perplexity) / 2,
            perplexities={"lower": out_lower.perplexity, "upper": out_upper.perplexity},
        )

    @torch.no_grad()
    def encode(self, motion: torch.Tensor) -> torch.Tensor:
        """Code indices (B, T // 4, 2) of motion (B, T, 263): [..., 0] lower, [..., 1] upper."""
        lower, upper = split_parts(motion)
        return torch.stack((self.lower.encode(lower), self.upper.encode(upper)), dim=-1)

    @torch.no_grad()
    def candidate_codes(self, motion: torch.Tensor, k: int) -> torch.Tensor:
        """The k codes (B, T // 4, 2, k) of each codebook nearest each latent of motion (B, T, 263)."""
        lower, upper = split_parts(motion)
        return torch.stack(
            (self.lower.candidate_codes(lower, k), self.upper.candidate_codes(upper, k)), dim=2
        )

    @torch.no_grad()
    def decode(self, indices: torch.Tensor, features: int | None = None) -> torch.Tensor:
        """Motion (B, T' * 4, 263) of code index pairs (B, T', 2); with `features`, its first
        `features` of 263 (both parts are decoded whole: the first features mix lower and upper)."""
        if indices.dim() != 3 or indices.shape[-1] != len(PARTS):
            raise ValueError(
                "a part-aware tokenizer decodes index pairs (B, T', 2) (lower, upper), got shape "
                f"{tuple(indices.shape)}"
            )
        motion = self.reconstruct(indices)
        return motion if features is None else motion[..., :features]

    def reconstruct(self, indices: torch.Tensor) -> torch.Tensor:
        """`decode` with gradients to both decoders (the decoder refinement trains them alone)."""
        return merge_parts(self.lower.reconstruct(indices[..., 0]), self.upper.reconstruct(indices[..., 1]))

    @torch.no_grad()
    def decode_parts(self, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
        """Motion (B, T' * 4, 263) of lower-body codes (B, T') and upper-body codes (B, T'),
        which may come from different motions."""
        if lower.shape != upper.shape:
            raise ValueError(
                f"lower and upper codes must have the same shape (B, T'), got {tuple(lower.shape)} and "
                f"{tuple(upper.shape)}"
            )
        return merge_parts(self.lower.decode(lower), self.upper.decode(upper))

    @property
    def quantizers(self) -> dict[str, EMAQuantizer]:
        """The codebooks by part name."""
        return {"lower": self.lower.quantizer, "upper": self.upper.quantizer}

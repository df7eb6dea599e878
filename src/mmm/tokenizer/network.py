"""The motion tokenizer (VQ-VAE): 1-D convolutional encoder, EMA quantizer, decoder.

Motion (B, T, D) -> latents (B, C, T/4) -> code indices (B, T/4) -> motion (B, T, D).
Sizes come from `TokenizerConfig` (the `tokenizer` part of conf/model/tiny.yaml, paper.yaml); `paper` is
method.md's table.
`part_aware` selects `PartAwareTokenizer` (mmm.tokenizer.parts): one such tokenizer per body part.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from mmm.tokenizer.quantizer import EMAQuantizer, QuantizerOutput


@dataclass
class TokenizerConfig:
    width: int = 512  # W
    num_codes: int = 8192  # K
    code_dim: int = 32  # C
    down_t: int = 2  # temporal downsampling 2**down_t
    depth: int = 3  # residual blocks per stack
    dilation_growth: int = 3
    ema_decay: float = 0.99
    l2_normalize: bool = False
    part_aware: bool = False  # lower and upper body tokenized separately (two codebooks)

    @property
    def downsample(self) -> int:
        return 2**self.down_t


class ResidualBlock(nn.Module):
    """Pre-activation: x + conv1x1(relu(conv3(relu(x), dilation)))."""

    def __init__(self, width: int, dilation: int):
        super().__init__()
        self.conv = nn.Conv1d(width, width, 3, padding=dilation, dilation=dilation)
        self.proj = nn.Conv1d(width, width, 1)
        self.act = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.proj(self.act(self.conv(self.act(x))))


def residual_stack(width: int, depth: int, growth: int) -> nn.Sequential:
    """`depth` blocks with dilations growth**i applied largest first (9, 3, 1)."""
    return nn.Sequential(*[ResidualBlock(width, growth**i) for i in reversed(range(depth))])


class Encoder(nn.Module):
    """(B, D, T) -> (B, C, T / 2**down_t)."""

    def __init__(self, in_dim: int, cfg: TokenizerConfig):
        super().__init__()
        W = cfg.width
        layers: list[nn.Module] = [nn.Conv1d(in_dim, W, 3, padding=1), nn.ReLU()]
        for _ in range(cfg.down_t):
            layers += [
                nn.Conv1d(W, W, 4, stride=2, padding=1),
                residual_stack(W, cfg.depth, cfg.dilation_growth),
            ]
        layers.append(nn.Conv1d(W, cfg.code_dim, 3, padding=1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class Decoder(nn.Module):
    """(B, C, T') -> (B, D, T' * 2**down_t)."""

    def __init__(self, out_dim: int, cfg: TokenizerConfig):
        super().__init__()
        W = cfg.width
        layers: list[nn.Module] = [nn.Conv1d(cfg.code_dim, W, 3, padding=1), nn.ReLU()]
        for _ in range(cfg.down_t):
            layers += [
                residual_stack(W, cfg.depth, cfg.dilation_growth),
                nn.Upsample(scale_factor=2, mode="nearest"),
                nn.Conv1d(W, W, 3, padding=1),
            ]
        layers += [nn.Conv1d(W, W, 3, padding=1), nn.ReLU(), nn.Conv1d(W, out_dim, 3, padding=1)]
        self.net = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor, features: int | None = None) -> torch.Tensor:
        """features: only the first `features` output channels (B, features, T), each the same to
        the bit as the full output's; the last convolution's other rows are never computed."""
        # float32 also from a bfloat16 autocast: the losses and the joints integrate the root from it.
        if features is None:
            return self.net(z).float()
        last = self.net[-1]
        x = self.net[:-1](z)
        return F.conv1d(x, last.weight[:features], last.bias[:features], padding=last.padding).float()

    def forward_lengths(self, z: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """`forward` of a batch of mixed lengths (B, C, T') with (B,) valid steps each: every
        convolution reads zeros past a row's end (zeroed after each layer), as it reads its own
        zero padding when the row is decoded alone; so the valid frames are those of decoding each
        row alone (to float rounding), in one call. Past a row's end: zeros."""

        def keep(x: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
            return x * (torch.arange(x.shape[-1], device=x.device)[None] < n[:, None]).unsqueeze(1).to(
                x.dtype
            )

        n = lengths.to(z.device)
        x = keep(z, n)
        for layer in self.net:
            blocks = layer if isinstance(layer, nn.Sequential) else [layer]
            for block in blocks:
                x = block(x)
                if isinstance(block, nn.Upsample):
                    n = n * int(block.scale_factor)
                x = keep(x, n)
        return x.float()


@dataclass
class TokenizerOutput:
    reconstruction: torch.Tensor  # (B, T, D)
    indices: torch.Tensor  # (B, T'), or (B, T', 2) for a part-aware tokenizer
    commit_loss: torch.Tensor
    perplexity: torch.Tensor  # mean over codebooks
    perplexities: dict[str, torch.Tensor]  # per codebook, keyed like `quantizers`


class MotionTokenizer(nn.Module):
    """Normalized motion features (B, T, D) <-> code indices (B, T / 4)."""

    part_aware = False  # one codebook for the whole body (PartAwareTokenizer: one per part)

    def __init__(self, feature_dim: int, cfg: TokenizerConfig):
        super().__init__()
        self.feature_dim, self.cfg = feature_dim, cfg
        self.encoder = Encoder(feature_dim, cfg)
        self.quantizer = EMAQuantizer(cfg.num_codes, cfg.code_dim, cfg.ema_decay, cfg.l2_normalize)
        self.decoder = Decoder(feature_dim, cfg)

    def forward(self, motion: torch.Tensor) -> TokenizerOutput:
        z = self.encoder(motion.transpose(1, 2))
        q: QuantizerOutput = self.quantizer(z)
        recon = self.decoder(q.quantized).transpose(1, 2)
        return TokenizerOutput(recon, q.indices, q.commit_loss, q.perplexity, {"": q.perplexity})

    @torch.no_grad()
    def encode(self, motion: torch.Tensor) -> torch.Tensor:
        """Code indices (B, T // 4) of motion (B, T, D)."""
        return self.quantizer.quantize(self.encoder(motion.transpose(1, 2)))

    @torch.no_grad()
    def candidate_codes(self, motion: torch.Tensor, k: int) -> torch.Tensor:
        """The k codes (B, T // 4, k) nearest each latent of motion (B, T, D), nearest first."""
        return self.quantizer.nearest_codes(self.encoder(motion.transpose(1, 2)), k)

    @torch.no_grad()
    def decode(self, indices: torch.Tensor, features: int | None = None) -> torch.Tensor:
        """Motion (B, T' * 4, D) of code indices (B, T'); with `features`, only the first
        `features` of D (B, T' * 4, features), computed alone (the code search's joints read 67 of 263)."""
        if features is not None:
            return self.decoder(self.quantizer.lookup(indices), features).transpose(1, 2)
        return self.reconstruct(indices)

    def reconstruct(self, indices: torch.Tensor) -> torch.Tensor:
        """`decode` with gradients to the decoder (the decoder refinement trains it alone)."""
        return self.decoder(self.quantizer.lookup(indices)).transpose(1, 2)

    @torch.no_grad()
    def decode_lengths(self, indices: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Motion (B, T' * 4, D) of code indices (B, T') padded past each row's `lengths` (B,):
        one decoder call for a mixed-length batch, each row's frames those `decode` gives it alone
        (to float rounding); frames past a row's 4 * length are zero."""
        return self.decoder.forward_lengths(self.quantizer.lookup(indices), lengths).transpose(1, 2)

    @property
    def quantizers(self) -> dict[str, EMAQuantizer]:
        """The codebooks by name; one, unnamed, so callers loop alike over this and a part-aware tokenizer."""
        return {"": self.quantizer}

    @property
    def codebook(self) -> torch.Tensor:
        """(K, C) code vectors; stage 2 embeds tokens with them."""
        return self.quantizer.codebook

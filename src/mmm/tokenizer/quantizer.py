"""EMA vector quantizer with codebook reset, all state in buffers, distributed sync built in.

Codes are updated by an exponential moving average of the latents assigned to them (decay 0.99):
codebook = ema_sum / ema_count. The first training batch seeds the codebook from encoder
latents. `reset_unused()` replaces the codes that no latent used since the previous reset by
latents of the latest batch, and re-seeds their EMA statistics so they survive the next update;
the caller decides how often (the `CodebookReset` callback: every N steps).

Under torch.distributed every rank ends every step with the same state: assignment counts and
sums are all-reduced before the EMA update, usage is counted from the reduced counts, and the
latents that seed or reset codes are chosen on rank 0 and broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn


def _distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def _all_reduce_sum(t: torch.Tensor) -> torch.Tensor:
    if _distributed():
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t


def _broadcast_from_rank0(t: torch.Tensor) -> torch.Tensor:
    if _distributed():
        dist.broadcast(t, src=0)
    return t


@dataclass
class QuantizerOutput:
    quantized: torch.Tensor  # (B, C, T') straight-through
    indices: torch.Tensor  # (B, T')
    commit_loss: torch.Tensor  # scalar
    perplexity: torch.Tensor  # scalar, of this batch's code usage (all ranks)


class EMAQuantizer(nn.Module):
    """Nearest-code quantization of latents (B, C, T') into `num_codes` codes of `code_dim`.

    l2_normalize: compare and store unit vectors (cosine lookup).
    """

    def __init__(
        self,
        num_codes: int = 8192,
        code_dim: int = 32,
        decay: float = 0.99,
        l2_normalize: bool = False,
        eps: float = 1e-5,
    ):
        super().__init__()
        self.num_codes, self.code_dim, self.decay, self.l2_normalize, self.eps = (
            num_codes,
            code_dim,
            decay,
            l2_normalize,
            eps,
        )
        self.register_buffer("codebook", torch.zeros(num_codes, code_dim))
        self.register_buffer("ema_sum", torch.zeros(num_codes, code_dim))
        self.register_buffer("ema_count", torch.zeros(num_codes))
        self.register_buffer("window_usage", torch.zeros(num_codes))  # assignments since the last reset
        self.register_buffer("initialized", torch.tensor(False))
        self._latest_latents: torch.Tensor | None = None  # (N, C) of the last training batch, this rank
        self.latest_counts: torch.Tensor | None = (
            None  # (K,) assignments of the last training step, all ranks
        )

    # -- lookup ---------------------------------------------------------------------------------
    def _flatten(self, z: torch.Tensor) -> torch.Tensor:
        # float32 under a bfloat16 autocast too: the codebook, its EMA and the choice of code stay exact.
        flat = z.permute(0, 2, 1).reshape(-1, self.code_dim).float()
        return F.normalize(flat, dim=-1) if self.l2_normalize else flat

    def _distances(self, flat: torch.Tensor) -> torch.Tensor:
        """Squared L2 distances (N, K) of latents (N, C) to every code, in float32 (also under autocast,
        whose bfloat16 matmul would pick among near codes by rounding)."""
        codebook = self.codebook.to(flat.dtype)
        with torch.autocast(flat.device.type, enabled=False):
            return flat.pow(2).sum(-1, keepdim=True) - 2 * flat @ codebook.t() + codebook.pow(2).sum(-1)[None]

    def nearest(self, flat: torch.Tensor) -> torch.Tensor:
        """Index (N,) of the nearest code (L2) of each latent (N, C)."""
        return self._distances(flat).argmin(dim=-1)

    def nearest_codes(self, z: torch.Tensor, k: int) -> torch.Tensor:
        """Indices (B, T', k) of the k codes nearest each latent of z (B, C, T'), nearest first
        (at most num_codes); what the code search (mmm.tokenizer.search) tries."""
        distances = self._distances(self._flatten(z))
        nearest = distances.topk(min(k, self.num_codes), dim=-1, largest=False).indices
        nearest[:, 0] = distances.argmin(dim=-1)  # on ties, the code `quantize` picks comes first
        return nearest.view(z.shape[0], z.shape[2], -1)

    def lookup(self, indices: torch.Tensor) -> torch.Tensor:
        """Code vectors (B, C, T') of indices (B, T')."""
        return F.embedding(indices, self.codebook).permute(0, 2, 1)

    def quantize(self, z: torch.Tensor) -> torch.Tensor:
        """Indices (B, T') of latents (B, C, T'); no state changes."""
        return self.nearest(self._flatten(z)).view(z.shape[0], z.shape[2])

    # -- training state ---------------------------------------------------------------------------
    @torch.no_grad()
    def _pick_latents(self, flat: torch.Tensor, n: int) -> torch.Tensor:
        """n latents (n, C) drawn on rank 0 from its batch (tiled with small noise when short) and
        broadcast, so every rank writes the same vectors."""
        if flat.shape[0] >= n:
            picked = flat[torch.randperm(flat.shape[0], device=flat.device)[:n]]
        else:
            repeats = (n + flat.shape[0] - 1) // flat.shape[0]
            tiled = flat.repeat(repeats, 1)[:n]
            picked = tiled + torch.randn_like(tiled) * (0.01 / max(self.code_dim, 1) ** 0.5)
        picked = picked.float().contiguous()
        return _broadcast_from_rank0(picked)

    @torch.no_grad()
    def _initialize(self, flat: torch.Tensor) -> None:
        codes = self._pick_latents(flat, self.num_codes)
        self.codebook.copy_(codes)
        self.ema_sum.copy_(codes)
        self.ema_count.fill_(1.0)
        self.initialized.fill_(True)

    @torch.no_grad()
    def _ema_update(self, flat: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
        onehot = F.one_hot(indices, self.num_codes).to(torch.float32)  # (N, K)
        counts = _all_reduce_sum(onehot.sum(0))
        sums = _all_reduce_sum(onehot.t() @ flat.float())
        self.ema_count.mul_(self.decay).add_(counts, alpha=1 - self.decay)
        self.ema_sum.mul_(self.decay).add_(sums, alpha=1 - self.decay)
        codebook = self.ema_sum / self.ema_count.clamp_min(self.eps).unsqueeze(-1)
        if self.l2_normalize:
            codebook = F.normalize(codebook, dim=-1)
        self.codebook.copy_(codebook)
        self.window_usage.add_(counts)
        return counts

    @torch.no_grad()
    def reset_unused(self) -> int:
        """Replace codes unused since the last reset by latents of the latest training batch.

        Returns the number of codes reset (the same on every rank). Clears the usage window.
        """
        if self._latest_latents is None or not bool(self.initialized):
            return 0
        unused = self.window_usage == 0
        n = int(unused.sum())
        if n:
            fresh = self._pick_latents(self._latest_latents, n).to(self.codebook.dtype)
            self.codebook[unused] = fresh
            # A count of 1 and the matching sum keep the new code in place through the next
            # EMA update even if nothing is assigned to it.
            self.ema_count[unused] = 1.0
            self.ema_sum[unused] = fresh
        self.window_usage.zero_()
        return n

    def forward(self, z: torch.Tensor) -> QuantizerOutput:
        flat = self._flatten(z)
        if self.training and not bool(self.initialized):
            self._initialize(flat.detach())
        indices = self.nearest(flat.detach())
        if self.training:
            self._latest_latents = flat.detach()
            counts = self._ema_update(flat.detach(), indices)
            self.latest_counts = counts
        else:
            counts = torch.bincount(indices, minlength=self.num_codes).float()
        quantized_flat = F.embedding(indices, self.codebook).to(flat.dtype)
        commit_loss = F.mse_loss(flat, quantized_flat.detach())
        quantized_flat = flat + (quantized_flat - flat).detach()  # straight-through
        B, _, T = z.shape
        quantized = quantized_flat.view(B, T, self.code_dim).permute(0, 2, 1)
        probs = counts / counts.sum().clamp_min(1.0)
        perplexity = torch.exp(-(probs * torch.log(probs + 1e-10)).sum())
        return QuantizerOutput(quantized, indices.view(B, T), commit_loss, perplexity)

    # -- statistics ------------------------------------------------------------------------------
    def window_active(self) -> int:
        """Codes used at least once since the last reset (the same on every rank)."""
        return int((self.window_usage > 0).sum())


def metric_name(group: str, codebook: str, name: str) -> str:
    """`<group>/<name>` for a tokenizer's only codebook (named ""), `<group>/<codebook>/<name>`
    for one of several (a part-aware tokenizer's "lower" and "upper")."""
    return f"{group}/{codebook}/{name}" if codebook else f"{group}/{name}"

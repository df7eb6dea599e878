"""Text-to-motion metrics on evaluator embeddings (evaluation.md, "Metrics").

R-Precision top-k, MM-Dist (matching score), FID, Diversity and MultiModality, as plain functions
and as torchmetrics `Metric` classes that accumulate over batches and synchronize across DDP
processes. Statistics are computed in float64 whatever the input dtype.

The formulas are those of the T2M / T2M-GPT / MMM evaluation code. Where that code draws random
pairs with numpy, these functions draw them with torch (`randperm`, two independent index sets
without replacement), so the same seed does not give the same pairs as the reference, only the
same distribution.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities.data import dim_zero_cat

__all__ = [
    "distance_matrix",
    "r_precision_hits",
    "matching_score",
    "gaussian_statistics",
    "frechet_distance",
    "fid",
    "diversity",
    "multimodality",
    "RPrecision",
    "FrechetDistance",
    "Diversity",
    "MultiModality",
]

_IMAGINARY_TOLERANCE = 1e-3


# --------------------------------------------------------------------------------------------
# Functional form
# --------------------------------------------------------------------------------------------


def _as_float64(x) -> Tensor:
    return torch.as_tensor(x).detach().to(torch.float64)


def _check_pairs(text: Tensor, motion: Tensor) -> None:
    if text.ndim != 2 or text.shape != motion.shape:
        raise ValueError(
            f"expected matched (B, D) text and motion embeddings, got {tuple(text.shape)} and "
            f"{tuple(motion.shape)}"
        )
    if text.shape[0] == 0:
        raise ValueError("expected at least one text-motion pair")


def distance_matrix(a: Tensor, b: Tensor) -> Tensor:
    """Euclidean distances between the rows of a (N, D) and b (M, D) -> (N, M), float64."""
    a, b = _as_float64(a), _as_float64(b)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"expected (N, D) and (M, D), got {tuple(a.shape)} and {tuple(b.shape)}")
    # The matrix-product expansion (|a|^2 + |b|^2 - 2ab) loses precision for close points.
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")


def _matched_distances(text: Tensor, motion: Tensor) -> Tensor:
    """(B,) distance between each text (B, D) and its own motion (B, D), float64."""
    return torch.linalg.vector_norm(_as_float64(text) - _as_float64(motion), dim=1)


def r_precision_hits(text: Tensor, motion: Tensor, top_k: int = 3) -> Tensor:
    """Hit counts of one batch of matched pairs (row i of text (B, D) matches row i of motion (B, D)).

    Returns a (top_k,) int64 tensor whose entry k-1 counts the texts whose own motion is among the
    k motions of the batch nearest to the text (cumulative in k). Ties are ordered by index, as a
    stable sort of each distance row would.
    """
    _check_pairs(text, motion)
    if top_k < 1:
        raise ValueError(f"top_k must be at least 1, got {top_k}")
    dist = distance_matrix(text, motion)
    order = torch.argsort(dist, dim=1, stable=True)
    own = torch.arange(dist.shape[0], device=dist.device)
    rank = (order == own[:, None]).to(torch.int64).argmax(dim=1)  # 0 = nearest
    ks = torch.arange(1, top_k + 1, device=dist.device)
    return (rank[None, :] < ks[:, None]).sum(dim=1)


def matching_score(text: Tensor, motion: Tensor) -> float:
    """MM-Dist: mean distance between each text (N, D) and its own motion (N, D)."""
    _check_pairs(text, motion)
    return float(_matched_distances(text, motion).mean())


def gaussian_statistics(emb: Tensor) -> tuple[Tensor, Tensor]:
    """Mean (D,) and covariance (D, D) with ddof 1 of embeddings (N, D), N >= 2, float64."""
    emb = _as_float64(emb)
    if emb.ndim != 2 or emb.shape[0] < 2:
        raise ValueError(f"expected (N, D) embeddings with N >= 2, got {tuple(emb.shape)}")
    return emb.mean(dim=0), torch.cov(emb.T, correction=1).reshape(emb.shape[1], emb.shape[1])


def _load_scipy_sqrtm():
    try:
        from scipy.linalg import sqrtm  # optional dependency (comes with mlflow)
    except ImportError:
        return None
    return sqrtm


def _eigen_sqrt_terms(sigma1: Tensor, sigma2: Tensor) -> Tensor:
    """Square roots of the eigenvalues of sqrt(sigma1)·sigma2·sqrt(sigma1) (complex, (D,)).

    That matrix is similar to sigma1·sigma2, so the terms sum to tr sqrtm(sigma1·sigma2); being
    symmetric, its eigenvalues come from a stable symmetric solver. sigma1 is taken as symmetric
    positive semi-definite (rounding below zero is clipped); a negative eigenvalue of the product
    gives an imaginary term, as a complex sqrtm would.
    """
    try:
        w, v = torch.linalg.eigh((sigma1 + sigma1.T) / 2)
        root1 = (v * w.clamp_min(0).sqrt()) @ v.T
        product = root1 @ sigma2 @ root1
        eigenvalues = torch.linalg.eigvalsh((product + product.T) / 2)
    except torch.linalg.LinAlgError:
        return torch.full((sigma1.shape[0],), float("nan"), dtype=torch.complex128)
    return torch.sqrt(eigenvalues.to(torch.complex128))


def _sqrt_product_terms(sigma1: Tensor, sigma2: Tensor) -> Tensor:
    """(D,) terms whose sum is tr sqrtm(sigma1·sigma2), complex or real, float64 precision.

    With scipy: the diagonal of scipy.linalg.sqrtm(sigma1·sigma2), as the reference computes it.
    Without: `_eigen_sqrt_terms`.
    """
    sqrtm = _load_scipy_sqrtm()
    if sqrtm is None:
        return _eigen_sqrt_terms(sigma1, sigma2)
    root = sqrtm((sigma1 @ sigma2).cpu().numpy())
    return torch.from_numpy(root.diagonal().copy())


def frechet_distance(mu1, sigma1, mu2, sigma2, eps: float = 1e-6) -> float:
    """Fréchet distance between N(mu1 (D,), sigma1 (D, D)) and N(mu2, sigma2).

    |mu1 - mu2|^2 + tr(sigma1) + tr(sigma2) - 2 tr sqrtm(sigma1·sigma2). When the square root is
    not finite, it is retried with eps·I added to both covariances. An imaginary part above 1e-3
    raises ValueError; a smaller one is dropped.
    """
    mu1, mu2 = _as_float64(mu1).reshape(-1).cpu(), _as_float64(mu2).reshape(-1).cpu()
    sigma1, sigma2 = torch.atleast_2d(_as_float64(sigma1).cpu()), torch.atleast_2d(_as_float64(sigma2).cpu())
    d = mu1.shape[0]
    if mu2.shape != (d,) or sigma1.shape != (d, d) or sigma2.shape != (d, d):
        raise ValueError(
            f"shapes do not agree: mu1 {tuple(mu1.shape)}, sigma1 {tuple(sigma1.shape)}, mu2 "
            f"{tuple(mu2.shape)}, sigma2 {tuple(sigma2.shape)}"
        )
    for name, value in (("mu1", mu1), ("sigma1", sigma1), ("mu2", mu2), ("sigma2", sigma2)):
        if not torch.isfinite(value).all():
            raise ValueError(f"{name} has non-finite entries")
    diff = mu1 - mu2
    terms = _sqrt_product_terms(sigma1, sigma2)
    if not torch.isfinite(terms).all():
        offset = eps * torch.eye(d, dtype=torch.float64)
        terms = _sqrt_product_terms(sigma1 + offset, sigma2 + offset)
        if not torch.isfinite(terms).all():
            raise ValueError(
                f"the matrix square root of sigma1·sigma2 is not finite, even with {eps:g}·I added to the "
                "covariances"
            )
    if terms.is_complex():
        imaginary = float(terms.imag.abs().max())
        if imaginary > _IMAGINARY_TOLERANCE:
            raise ValueError(
                f"the matrix square root of sigma1·sigma2 has an imaginary component {imaginary:.4g} "
                f"(tolerance {_IMAGINARY_TOLERANCE:g})"
            )
        terms = terms.real
    # A distance: rounding makes identical distributions come out around -1e-7, reported as 0.
    return max(0.0, float(diff @ diff + torch.trace(sigma1) + torch.trace(sigma2) - 2 * terms.sum()))


def fid(real: Tensor, generated: Tensor) -> float:
    """FID between real (N, D) and generated (M, D) embeddings (N, M >= 2)."""
    mu1, sigma1 = gaussian_statistics(real)
    mu2, sigma2 = gaussian_statistics(generated)
    return frechet_distance(mu1, sigma1, mu2, sigma2)


def _draw_pairs(n: int, times: int, generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """Two index sets of `times` indices in [0, n), each without replacement, drawn independently."""
    device = generator.device if generator is not None else torch.device("cpu")
    first = torch.randperm(n, generator=generator, device=device)[:times]
    second = torch.randperm(n, generator=generator, device=device)[:times]
    return first, second


def diversity(emb: Tensor, times: int = 300, generator: torch.Generator | None = None) -> float:
    """Mean distance over `times` random pairs of embeddings (N, D), N >= times.

    The pairs join two index sets drawn independently without replacement (a pair may join an
    embedding with itself). `generator` None uses torch's global generator.
    """
    emb = _as_float64(emb)
    if emb.ndim != 2:
        raise ValueError(f"expected (N, D) embeddings, got {tuple(emb.shape)}")
    if times < 1:
        raise ValueError(f"times must be at least 1, got {times}")
    if emb.shape[0] < times:
        raise ValueError(
            f"diversity draws times={times} embeddings without replacement but got only N={emb.shape[0]}"
        )
    first, second = _draw_pairs(emb.shape[0], times, generator)
    first, second = first.to(emb.device), second.to(emb.device)
    return float(torch.linalg.vector_norm(emb[first] - emb[second], dim=1).mean())


def multimodality(emb: Tensor, times: int = 10, generator: torch.Generator | None = None) -> float:
    """Mean distance over `times` random pairs of generations of the same text; emb (N, R, D) holds
    R generations for each of N texts, R >= times.

    One pair of index sets (each drawn without replacement from the R generations) serves all
    texts, as in the reference. `generator` None uses torch's global generator.
    """
    emb = _as_float64(emb)
    if emb.ndim != 3 or emb.shape[0] == 0:
        raise ValueError(f"expected (N, R, D) embeddings with N >= 1, got {tuple(emb.shape)}")
    if times < 1:
        raise ValueError(f"times must be at least 1, got {times}")
    if emb.shape[1] < times:
        raise ValueError(
            f"multimodality draws times={times} generations per text without replacement but got only "
            f"R={emb.shape[1]}"
        )
    first, second = _draw_pairs(emb.shape[1], times, generator)
    first, second = first.to(emb.device), second.to(emb.device)
    return float(torch.linalg.vector_norm(emb[:, first] - emb[:, second], dim=2).mean())


# --------------------------------------------------------------------------------------------
# torchmetrics classes
# --------------------------------------------------------------------------------------------


class RPrecision(Metric):
    """R-Precision top-1..top_k and MM-Dist over batches of matched pairs.

    update(text (B, D), motion (B, D)): one batch (the protocol uses 32 pairs, drop_last); the
    ranking is within the batch. compute() -> {"top1": ..., "top<top_k>": ..., "matching_score": ...}
    (float64 scalars): hits summed over all batches (and processes) divided by the number of pairs,
    and the mean distance between each text and its own motion.
    """

    full_state_update = False
    is_differentiable = False
    higher_is_better = None  # top-k: higher; matching score: lower

    def __init__(self, top_k: int = 3, **kwargs):
        super().__init__(**kwargs)
        if top_k < 1:
            raise ValueError(f"top_k must be at least 1, got {top_k}")
        self.top_k = top_k
        self.add_state("hits", default=torch.zeros(top_k, dtype=torch.int64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.tensor(0, dtype=torch.int64), dist_reduce_fx="sum")
        self.add_state("distance_sum", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, text: Tensor, motion: Tensor) -> None:
        self.hits += r_precision_hits(text, motion, self.top_k).to(self.hits.device)
        self.count += text.shape[0]
        self.distance_sum += _matched_distances(text, motion).sum().to(self.distance_sum.device)

    def compute(self) -> dict[str, Tensor]:
        if int(self.count) == 0:
            raise ValueError("RPrecision.compute() before any update")
        count = self.count.to(torch.float64)
        out = {f"top{k + 1}": self.hits[k].to(torch.float64) / count for k in range(self.top_k)}
        out["matching_score"] = self.distance_sum.to(torch.float64) / count
        return out


class FrechetDistance(Metric):
    """FID between real and generated embeddings of width `dim`, from sufficient statistics.

    update(real (B, D) | None, generated (B', D) | None): either side may be left out. The states
    (sums, sums of outer products, counts, float64) are summed across processes, so the result
    equals `fid` on all the embeddings up to rounding. compute() -> float64 scalar.
    """

    full_state_update = False
    is_differentiable = False
    higher_is_better = False

    def __init__(self, dim: int, **kwargs):
        super().__init__(**kwargs)
        self.dim = dim
        for side in ("real", "generated"):
            self.add_state(f"{side}_sum", default=torch.zeros(dim, dtype=torch.float64), dist_reduce_fx="sum")
            self.add_state(
                f"{side}_outer", default=torch.zeros(dim, dim, dtype=torch.float64), dist_reduce_fx="sum"
            )
            self.add_state(f"{side}_count", default=torch.tensor(0, dtype=torch.int64), dist_reduce_fx="sum")

    def _accumulate(self, side: str, emb: Tensor) -> None:
        emb = _as_float64(emb).to(self.real_sum.device)
        if emb.ndim != 2 or emb.shape[1] != self.dim:
            raise ValueError(f"expected ({side} batch, {self.dim}) embeddings, got {tuple(emb.shape)}")
        setattr(self, f"{side}_sum", getattr(self, f"{side}_sum") + emb.sum(dim=0))
        setattr(self, f"{side}_outer", getattr(self, f"{side}_outer") + emb.T @ emb)
        setattr(self, f"{side}_count", getattr(self, f"{side}_count") + emb.shape[0])

    def update(self, real: Tensor | None = None, generated: Tensor | None = None) -> None:
        if real is None and generated is None:
            raise ValueError("FrechetDistance.update needs real or generated embeddings")
        if real is not None:
            self._accumulate("real", real)
        if generated is not None:
            self._accumulate("generated", generated)

    def _gaussian(self, side: str) -> tuple[Tensor, Tensor]:
        n = int(getattr(self, f"{side}_count"))
        if n < 2:
            raise ValueError(f"FID needs at least 2 {side} embeddings, got {n}")
        total, outer = (
            getattr(self, f"{side}_sum").to(torch.float64),
            getattr(self, f"{side}_outer").to(torch.float64),
        )
        mean = total / n
        cov = (outer - n * torch.outer(mean, mean)) / (n - 1)
        return mean, (cov + cov.T) / 2

    def compute(self) -> Tensor:
        mu1, sigma1 = self._gaussian("real")
        mu2, sigma2 = self._gaussian("generated")
        return torch.tensor(frechet_distance(mu1, sigma1, mu2, sigma2), dtype=torch.float64)


class Diversity(Metric):
    """Diversity of all the embeddings seen: update(emb (B, D)); compute() -> float64 scalar.

    The embeddings are kept and gathered across processes in rank order; the pairs are drawn by a
    generator seeded with `seed` at every compute, so every rank computes the same value.
    """

    full_state_update = False
    is_differentiable = False
    higher_is_better = None  # closer to the real motions' diversity is better

    def __init__(self, times: int = 300, seed: int = 0, **kwargs):
        super().__init__(**kwargs)
        self.times, self.seed = times, seed
        self.add_state("embeddings", default=[], dist_reduce_fx="cat")

    def update(self, emb: Tensor) -> None:
        if emb.ndim != 2:
            raise ValueError(f"expected (B, D) embeddings, got {tuple(emb.shape)}")
        self.embeddings.append(_as_float64(emb))

    def compute(self) -> Tensor:
        if isinstance(self.embeddings, list) and not self.embeddings:
            raise ValueError("Diversity.compute() before any update")
        generator = torch.Generator().manual_seed(self.seed)
        return torch.tensor(
            diversity(dim_zero_cat(self.embeddings), self.times, generator), dtype=torch.float64
        )


class MultiModality(Metric):
    """MultiModality of all the texts seen: update(emb (B, R, D)), R generations for each of B
    texts; compute() -> float64 scalar.

    Kept, gathered and seeded as in `Diversity`, so every rank computes the same value.
    """

    full_state_update = False
    is_differentiable = False
    higher_is_better = None

    def __init__(self, times: int = 10, seed: int = 0, **kwargs):
        super().__init__(**kwargs)
        self.times, self.seed = times, seed
        self.add_state("embeddings", default=[], dist_reduce_fx="cat")

    def update(self, emb: Tensor) -> None:
        if emb.ndim != 3:
            raise ValueError(f"expected (B, R, D) embeddings, got {tuple(emb.shape)}")
        self.embeddings.append(_as_float64(emb))

    def compute(self) -> Tensor:
        if isinstance(self.embeddings, list) and not self.embeddings:
            raise ValueError("MultiModality.compute() before any update")
        generator = torch.Generator().manual_seed(self.seed)
        return torch.tensor(
            multimodality(dim_zero_cat(self.embeddings), self.times, generator), dtype=torch.float64
        )

import math

import numpy as np
import pytest
import torch

from mmm.evaluation import metrics
from mmm.evaluation.metrics import (
    Diversity,
    FrechetDistance,
    MultiModality,
    RPrecision,
    distance_matrix,
    diversity,
    fid,
    frechet_distance,
    gaussian_statistics,
    matching_score,
    multimodality,
    r_precision_hits,
)
from tests.helpers import run_ddp_worker

# Four texts and four motions in 2-D. Squared distances (rows: texts, columns: motions):
#   t0 (0,0): m0 1,  m1 25, m2 13, m3 20 -> own motion m0 is the 1st nearest
#   t1 (4,0): m0 17, m1 9,  m2 5,  m3 52 -> own motion m1 is the 2nd nearest (after m2)
#   t2 (0,4): m0 9,  m1 17, m2 13, m3 4  -> own motion m2 is the 3rd nearest (after m3, m0)
#   t3 (4,4): m0 25, m1 1,  m2 5,  m3 36 -> own motion m3 is the 4th nearest
TEXTS = torch.tensor([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0], [4.0, 4.0]])
MOTIONS = torch.tensor([[0.0, 1.0], [4.0, 3.0], [3.0, 2.0], [-2.0, 4.0]])
OWN_DISTANCES = [1.0, 3.0, math.sqrt(13.0), 6.0]


@pytest.fixture(params=["scipy", "eigen"])
def sqrt_route(request, monkeypatch):
    """Runs a test with scipy's sqrtm and with the eigen-decomposition fallback."""
    if request.param == "scipy":
        pytest.importorskip("scipy")
    else:
        monkeypatch.setattr(metrics, "_load_scipy_sqrtm", lambda: None)
    return request.param


def _random_spd(d, seed, scale=1.0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(d, d, generator=g, dtype=torch.float64)
    return scale * (a @ a.T / d + 0.1 * torch.eye(d, dtype=torch.float64))


def _rotation(d, seed):
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(d, d, generator=g, dtype=torch.float64))
    return q


# ---------------------------------------------------------------- distances, R-precision, MM-Dist


def test_distance_matrix_is_euclidean_in_float64():
    a = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=torch.float32)
    b = torch.tensor([[3.0, 4.0], [1.0, 1.0], [0.0, -2.0]], dtype=torch.float32)
    d = distance_matrix(a, b)
    assert d.dtype == torch.float64 and d.shape == (2, 3)
    expected = [[5.0, math.sqrt(2.0), 2.0], [math.sqrt(4 + 9), 0.0, math.sqrt(1 + 9)]]
    assert torch.allclose(d, torch.tensor(expected, dtype=torch.float64), atol=1e-12)


def test_distance_matrix_keeps_precision_for_close_far_points():
    # Far from the origin, |a|^2 + |b|^2 - 2ab would cancel to rounding noise.
    a = torch.tensor([[1e4, 1e4]], dtype=torch.float64)
    b = a + torch.tensor([[1e-5, 0.0]], dtype=torch.float64)
    assert distance_matrix(a, b).item() == pytest.approx(1e-5, rel=1e-6)


def test_r_precision_hits_hand_checked():
    assert r_precision_hits(TEXTS, MOTIONS, top_k=4).tolist() == [1, 2, 3, 4]
    assert r_precision_hits(TEXTS, MOTIONS, top_k=3).tolist() == [1, 2, 3]
    assert r_precision_hits(TEXTS, MOTIONS, top_k=1).tolist() == [1]
    # Motions in the text order: every text finds its own motion first.
    assert r_precision_hits(TEXTS, TEXTS + 0.1, top_k=3).tolist() == [4, 4, 4]


def test_r_precision_ties_are_ordered_by_index():
    text = torch.zeros(4, 2)
    motion = torch.ones(4, 2)  # every motion at the same distance from every text
    # Text i's own motion sits at position i of the stable order: hits only for i < k.
    assert r_precision_hits(text, motion, top_k=3).tolist() == [1, 2, 3]


def test_matching_score_hand_checked():
    assert matching_score(TEXTS, MOTIONS) == pytest.approx(sum(OWN_DISTANCES) / 4, abs=1e-12)
    assert matching_score(TEXTS, TEXTS) == 0.0


def test_pair_shape_errors():
    with pytest.raises(ValueError, match="matched"):
        r_precision_hits(TEXTS, MOTIONS[:3])
    with pytest.raises(ValueError, match="matched"):
        matching_score(TEXTS, MOTIONS[:, :1])


# ---------------------------------------------------------------- Gaussian fits and FID


def test_gaussian_statistics_match_numpy():
    x = np.random.default_rng(0).normal(size=(50, 5))
    mean, cov = gaussian_statistics(torch.from_numpy(x).float())
    assert mean.dtype == cov.dtype == torch.float64
    assert np.allclose(mean.numpy(), x.astype(np.float32).mean(0), atol=1e-6)
    assert np.allclose(cov.numpy(), np.cov(x.astype(np.float32), rowvar=False, ddof=1), atol=1e-6)
    with pytest.raises(ValueError):
        gaussian_statistics(torch.zeros(1, 5))


def test_frechet_same_covariance_is_squared_mean_distance(sqrt_route):
    sigma = _random_spd(6, 0)
    mu1 = torch.tensor([0.0, 1.0, 2.0, -1.0, 0.5, 3.0], dtype=torch.float64)
    mu2 = torch.tensor([1.0, 1.0, 0.0, 1.0, 0.5, 0.0], dtype=torch.float64)
    assert frechet_distance(mu1, sigma, mu2, sigma) == pytest.approx(
        float((mu1 - mu2) @ (mu1 - mu2)), abs=1e-8
    )
    assert float((mu1 - mu2) @ (mu1 - mu2)) == 1 + 4 + 4 + 9


def test_fid_of_shifted_samples_is_squared_shift(sqrt_route):
    g = torch.Generator().manual_seed(1)
    x = torch.randn(400, 6, generator=g, dtype=torch.float64) @ torch.randn(
        6, 6, generator=g, dtype=torch.float64
    )
    shift = torch.tensor([3.0, 0.0, -4.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    assert fid(x, x + shift) == pytest.approx(25.0, abs=1e-7)
    assert abs(fid(x, x)) < 1e-8


def test_frechet_matches_closed_form_for_commuting_covariances(sqrt_route):
    # sigma = Q diag(v) Q^T with one rotation Q: tr sqrt(s1 s2) = sum sqrt(a b), so
    # FID = |dmu|^2 + sum (sqrt(a) - sqrt(b))^2.
    a = torch.tensor([1.0, 4.0, 0.25, 9.0, 2.0], dtype=torch.float64)
    b = torch.tensor([4.0, 1.0, 1.0, 1.0, 8.0], dtype=torch.float64)
    mu1 = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0], dtype=torch.float64)
    mu2 = torch.tensor([1.0, 0.0, 3.0, 4.0, 4.0], dtype=torch.float64)
    expected = 4 + 1 + ((a.sqrt() - b.sqrt()) ** 2).sum().item()
    assert expected == pytest.approx(5 + 1 + 1 + 0.25 + 4 + 2)
    assert frechet_distance(mu1, torch.diag(a), mu2, torch.diag(b)) == pytest.approx(expected, abs=1e-10)
    q = _rotation(5, 3)
    rotated = frechet_distance(q @ mu1, q @ torch.diag(a) @ q.T, q @ mu2, q @ torch.diag(b) @ q.T)
    assert rotated == pytest.approx(expected, abs=1e-9)


def test_frechet_general_covariances_agree_with_eigenvalues_of_the_product(sqrt_route):
    s1, s2 = _random_spd(7, 10), _random_spd(7, 11, scale=3.0)
    mu1, mu2 = torch.zeros(7, dtype=torch.float64), torch.ones(7, dtype=torch.float64)
    # Independent route: tr sqrtm(s1 s2) = sum of square roots of the (real, positive) eigenvalues.
    eigenvalues = np.linalg.eigvals(s1.numpy() @ s2.numpy())
    assert np.abs(eigenvalues.imag).max() < 1e-9 and eigenvalues.real.min() > 0
    expected = 7 + np.trace(s1.numpy()) + np.trace(s2.numpy()) - 2 * np.sqrt(eigenvalues.real).sum()
    assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(expected, abs=1e-9)


def test_frechet_raises_on_large_imaginary_part(sqrt_route):
    # sigma1·sigma2 = diag(1, -1): its square root has the imaginary entry i.
    s1 = torch.eye(2, dtype=torch.float64)
    s2 = torch.diag(torch.tensor([1.0, -1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="imaginary component 1"):
        frechet_distance(torch.zeros(2), s1, torch.zeros(2), s2)


def test_frechet_drops_a_small_imaginary_part(monkeypatch):
    def sqrtm(a):
        return np.diag(np.sqrt(np.diag(a))) + 1e-5j

    monkeypatch.setattr(metrics, "_load_scipy_sqrtm", lambda: sqrtm)
    s1 = torch.diag(torch.tensor([1.0, 4.0], dtype=torch.float64))
    s2 = torch.diag(torch.tensor([4.0, 4.0], dtype=torch.float64))
    # |dmu|^2 = 1; traces 5 + 8; tr sqrt = 2 + 4.
    assert frechet_distance(torch.zeros(2), s1, torch.tensor([1.0, 0.0]), s2) == pytest.approx(
        1 + 13 - 12, abs=1e-12
    )


def test_frechet_retries_with_an_offset_when_the_root_is_not_finite(monkeypatch):
    calls = []

    def sqrtm(a):
        calls.append(a.copy())
        if len(calls) == 1:
            return np.full_like(a, np.nan)
        return np.diag(np.sqrt(np.diag(a)))

    monkeypatch.setattr(metrics, "_load_scipy_sqrtm", lambda: sqrtm)
    s1 = torch.diag(torch.tensor([1.0, 4.0], dtype=torch.float64))
    s2 = torch.diag(torch.tensor([9.0, 1.0], dtype=torch.float64))
    value = frechet_distance(torch.zeros(2), s1, torch.zeros(2), s2)
    assert len(calls) == 2
    eps = 1e-6
    assert np.allclose(calls[1], np.diag([(1 + eps) * (9 + eps), (4 + eps) * (1 + eps)]), rtol=0, atol=1e-15)
    expected = 15 - 2 * (math.sqrt((1 + eps) * (9 + eps)) + math.sqrt((4 + eps) * (1 + eps)))
    assert value == pytest.approx(expected, abs=1e-12) and value == pytest.approx(15 - 2 * (3 + 2), abs=1e-5)

    calls.clear()
    monkeypatch.setattr(metrics, "_load_scipy_sqrtm", lambda: lambda a: np.full_like(a, np.inf))
    with pytest.raises(ValueError, match="not finite"):
        frechet_distance(torch.zeros(2), s1, torch.zeros(2), s2)


def test_frechet_rejects_bad_inputs():
    with pytest.raises(ValueError, match="shapes"):
        frechet_distance(torch.zeros(2), torch.eye(2), torch.zeros(3), torch.eye(3))
    with pytest.raises(ValueError, match="non-finite"):
        frechet_distance(torch.tensor([0.0, float("nan")]), torch.eye(2), torch.zeros(2), torch.eye(2))


# ---------------------------------------------------------------- Diversity and MultiModality


def _line(n):
    """n points on the x axis at 0, 1, ..., n-1 (2-D, so the norm is over a real vector)."""
    return torch.stack((torch.arange(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)), dim=1)


def test_diversity_is_the_mean_over_the_drawn_pairs():
    n, times = 12, 7
    value = diversity(_line(n), times, torch.Generator().manual_seed(3))
    first, second = metrics._draw_pairs(n, times, torch.Generator().manual_seed(3))
    pairs = list(zip(first.tolist(), second.tolist()))
    assert len(pairs) == times
    assert len(set(first.tolist())) == times and len(set(second.tolist())) == times  # without replacement
    assert first.tolist() != second.tolist()  # two independent draws
    assert value == pytest.approx(sum(abs(i - j) for i, j in pairs) / times, abs=1e-12)


def test_diversity_with_times_equal_to_n_uses_every_point_once_per_side():
    n = 9
    first, second = metrics._draw_pairs(n, n, torch.Generator().manual_seed(0))
    assert sorted(first.tolist()) == sorted(second.tolist()) == list(range(n))
    # Points at the vertices of a regular simplex: every distinct pair is sqrt(2) apart.
    value = diversity(torch.eye(n), n, torch.Generator().manual_seed(0))
    distinct = sum(i != j for i, j in zip(first.tolist(), second.tolist()))
    assert value == pytest.approx(math.sqrt(2) * distinct / n, abs=1e-12)


def test_diversity_draws_are_uniform_and_independent():
    # Averaged over seeds, a pair is uniform over all n^2 ordered pairs (self-pairs included).
    x = _line(6)
    exact = sum(abs(i - j) for i in range(6) for j in range(6)) / 36
    mean = np.mean([diversity(x, 3, torch.Generator().manual_seed(s)) for s in range(400)])
    assert mean == pytest.approx(exact, abs=0.15)


def test_diversity_needs_times_points():
    with pytest.raises(ValueError, match=r"times=300.*N=299"):
        diversity(torch.zeros(299, 4), 300)
    assert diversity(torch.ones(300, 4), 300) == 0.0


def test_multimodality_pairs_only_generations_of_the_same_text():
    n_texts, r, times = 4, 11, 5
    # Generation k of text n lies at (n + 1)·k on its own line, far from the other texts' lines.
    emb = torch.zeros(n_texts, r, 3, dtype=torch.float64)
    for n in range(n_texts):
        emb[n, :, 0] = (n + 1) * torch.arange(r, dtype=torch.float64)
        emb[n, :, 1] = 1000.0 * n
    value = multimodality(emb, times, torch.Generator().manual_seed(4))
    first, second = metrics._draw_pairs(r, times, torch.Generator().manual_seed(4))
    assert len(set(first.tolist())) == len(set(second.tolist())) == times
    per_pair = sum(abs(i - j) for i, j in zip(first.tolist(), second.tolist())) / times
    assert value == pytest.approx(per_pair * sum(n + 1 for n in range(n_texts)) / n_texts, abs=1e-12)


def test_multimodality_needs_times_generations():
    with pytest.raises(ValueError, match=r"times=10.*R=9"):
        multimodality(torch.zeros(3, 9, 4), 10)
    with pytest.raises(ValueError, match="N, R, D"):
        multimodality(torch.zeros(3, 9), 2)


# ---------------------------------------------------------------- Metric classes


def _dataset(seed=0, n=160, d=6):
    g = torch.Generator().manual_seed(seed)
    text = torch.randn(n, d, generator=g)
    return {
        "text": text,
        "motion": text + 0.7 * torch.randn(n, d, generator=g),
        "real": torch.randn(n, d, generator=g) @ torch.randn(d, d, generator=g),
        "generated": torch.randn(n + 17, d, generator=g) * 1.4 - 0.2,
        "mm": torch.randn(9, 12, d, generator=g),
    }


@pytest.mark.filterwarnings("ignore:The ``compute`` method")
def test_r_precision_metric_hand_checked_and_batched():
    metric = RPrecision(top_k=3)
    metric.update(TEXTS, MOTIONS)
    out = metric.compute()
    assert set(out) == {"top1", "top2", "top3", "matching_score"}
    assert [out[f"top{k}"].item() for k in (1, 2, 3)] == [0.25, 0.5, 0.75]
    assert out["matching_score"].item() == pytest.approx(sum(OWN_DISTANCES) / 4, abs=1e-12)

    data = _dataset()
    batches = [slice(b * 32, (b + 1) * 32) for b in range(5)]
    metric = RPrecision(top_k=3)
    for rows in batches:
        metric.update(data["text"][rows], data["motion"][rows])
    out = metric.compute()
    hits = sum(r_precision_hits(data["text"][rows], data["motion"][rows], 3) for rows in batches)
    for k in range(3):
        assert out[f"top{k + 1}"].item() == hits[k].item() / 160
    assert 0 < hits[0] < hits[1] < hits[2] < 160
    assert out["matching_score"].item() == pytest.approx(
        matching_score(data["text"], data["motion"]), abs=1e-12
    )
    metric.reset()
    with pytest.raises(ValueError, match="before any update"):
        metric.compute()


def test_frechet_metric_equals_fid_in_one_or_several_batches():
    data = _dataset()
    expected = fid(data["real"], data["generated"])
    one = FrechetDistance(6)
    one.update(real=data["real"], generated=data["generated"])
    several = FrechetDistance(6)
    for lo, hi in ((0, 50), (50, 51), (51, 160)):
        several.update(real=data["real"][lo:hi])
    for lo, hi in ((0, 100), (100, 177)):
        several.update(generated=data["generated"][lo:hi])
    assert one.compute().item() == pytest.approx(expected, abs=1e-9)
    assert several.compute().item() == pytest.approx(expected, abs=1e-9)
    assert expected > 1.0
    with pytest.raises(ValueError, match="expected"):
        several.update(real=torch.zeros(3, 5))
    empty = FrechetDistance(6)
    empty.update(real=data["real"])
    with pytest.raises(ValueError, match="at least 2 generated"):
        empty.compute()


@pytest.mark.filterwarnings("ignore:The ``compute`` method")
def test_diversity_and_multimodality_metrics_equal_the_functions():
    data = _dataset()
    gen = data["generated"]
    expected = diversity(gen, 150, torch.Generator().manual_seed(9))
    one, several = Diversity(150, seed=9), Diversity(150, seed=9)
    one.update(gen)
    for lo, hi in ((0, 40), (40, 41), (41, 177)):
        several.update(gen[lo:hi])
    assert one.compute().item() == several.compute().item() == expected
    assert several.compute().item() == expected  # seeded at every compute
    assert Diversity(150, seed=10).forward(gen).item() != expected  # another seed, other pairs

    mm = data["mm"]
    expected = multimodality(mm, 10, torch.Generator().manual_seed(2))
    one, several = MultiModality(10, seed=2), MultiModality(10, seed=2)
    one.update(mm)
    several.update(mm[:4])
    several.update(mm[4:])
    assert one.compute().item() == several.compute().item() == expected
    with pytest.raises(ValueError, match="before any update"):
        MultiModality().compute()


def test_metric_states_reduce_by_sum_or_cat():
    assert set(RPrecision()._reductions) == {"hits", "count", "distance_sum"}
    for metric in (RPrecision(), FrechetDistance(4)):
        assert all(fx.__name__ == "dim_zero_sum" for fx in metric._reductions.values())
    for metric in (Diversity(), MultiModality()):
        assert [fx.__name__ for fx in metric._reductions.values()] == ["dim_zero_cat"]
        assert metric.full_state_update is False


# ---------------------------------------------------------------- DDP


@pytest.mark.slow
@pytest.mark.ddp
def test_metrics_synchronize_across_two_processes(tmp_path):
    r0, r1 = run_ddp_worker("metrics_ddp.py", tmp_path, out_dir=tmp_path, timeout=120)
    data = torch.load(tmp_path / "data.pt", weights_only=True)
    assert (r0["local_count"].item(), r1["local_count"].item()) == (192, 128)  # each rank saw only its part
    for key in ("top1", "top2", "top3", "matching_score", "fid", "diversity", "multimodality"):
        assert torch.equal(r0[key], r1[key]), key

    n = data["text"].shape[0]
    hits = sum(
        r_precision_hits(data["text"][b : b + 32], data["motion"][b : b + 32], 3) for b in range(0, n, 32)
    )
    for k in range(3):
        assert r0[f"top{k + 1}"].item() == hits[k].item() / n
    assert r0["matching_score"].item() == pytest.approx(
        matching_score(data["text"], data["motion"]), abs=1e-6
    )
    assert r0["fid"].item() == pytest.approx(fid(data["real"], data["generated"]), abs=1e-6)
    # Gathered in rank order = the dataset order, with the generators seeded as in the worker.
    assert r0["diversity"].item() == diversity(data["generated"], 300, torch.Generator().manual_seed(5))
    assert r0["multimodality"].item() == multimodality(data["mm"], 10, torch.Generator().manual_seed(7))

"""The metric classes under DDP: 2 CPU processes over gloo, each updating with part of a fixed dataset.

Run by tests/test_metrics.py as `python metrics_ddp.py OUT_DIR`. Rank 0 takes the first batches
of every dataset and rank 1 the rest (unequal parts, and fewer than `Diversity.times` embeddings
on either rank alone); each rank writes its computed values to OUT_DIR/rank{r}.pt and rank 0
writes the whole dataset to OUT_DIR/data.pt for the single-process comparison.
"""

import os
import sys

import torch
from gloo import spawn_two_ranks  # beside this script (its folder is on sys.path)

from mmm.evaluation.metrics import Diversity, FrechetDistance, MultiModality, RPrecision

BATCH = 32
BATCHES = 10  # 320 pairs: more than Diversity's 300 in total, fewer on each rank
RANK0_BATCHES = 6
MM_TEXTS, MM_GENERATIONS, MM_RANK0 = 20, 12, 12
DIM = 8


def make_data() -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1234)
    n = BATCH * BATCHES
    text = torch.randn(n, DIM, generator=g, dtype=torch.float64)
    return {
        "text": text,
        "motion": text + 0.8 * torch.randn(n, DIM, generator=g, dtype=torch.float64),
        "real": torch.randn(n, DIM, generator=g, dtype=torch.float64)
        @ torch.randn(DIM, DIM, generator=g, dtype=torch.float64),
        "generated": torch.randn(n, DIM, generator=g, dtype=torch.float64) * 1.5 + 0.3,
        "mm": torch.randn(MM_TEXTS, MM_GENERATIONS, DIM, generator=g, dtype=torch.float64),
    }


def work(rank: int, out_dir: str) -> None:
    data = make_data()
    if rank == 0:
        torch.save(data, os.path.join(out_dir, "data.pt"))
    batches = range(RANK0_BATCHES) if rank == 0 else range(RANK0_BATCHES, BATCHES)
    texts = slice(0, MM_RANK0) if rank == 0 else slice(MM_RANK0, MM_TEXTS)
    rprec, frechet, div, mm = (
        RPrecision(3),
        FrechetDistance(DIM),
        Diversity(300, seed=5),
        MultiModality(10, seed=7),
    )
    for b in batches:
        rows = slice(b * BATCH, (b + 1) * BATCH)
        rprec.update(data["text"][rows], data["motion"][rows])
        frechet.update(real=data["real"][rows], generated=data["generated"][rows])
        div.update(data["generated"][rows])
    # Two updates on each rank, so that the list state holds several tensors.
    mm_rank = data["mm"][texts]
    mm.update(mm_rank[:3])
    mm.update(mm_rank[3:])
    values = {
        **rprec.compute(),
        "fid": frechet.compute(),
        "diversity": div.compute(),
        "multimodality": mm.compute(),
    }
    values["local_count"] = rprec.count.clone()  # synced state is restored after compute
    torch.save({k: v.clone() for k, v in values.items()}, os.path.join(out_dir, f"rank{rank}.pt"))


if __name__ == "__main__":
    spawn_two_ranks(work, sys.argv[1])

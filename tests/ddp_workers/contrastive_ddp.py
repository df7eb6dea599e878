"""The evaluator's contrastive loss under DDP: 2 CPU processes over gloo, each holding part of one
fixed batch (rank 0 five pairs with up to two counterfactual captions each, rank 1 three pairs
with none, one of them a paraphrase of a rank-0 caption).

Run by tests/test_contrastive_evaluator.py as `python contrastive_ddp.py OUT_DIR`. Each rank
computes the module's training loss with global negatives, backpropagates, averages the gradients
over the ranks as DDP does, and writes the loss, the averaged gradients and its loss without
global negatives to OUT_DIR/rank{r}.pt; the test compares them with one process on the whole
batch (make_batch, make_module).
"""

import os
import sys

import torch
import torch.distributed as dist
from gloo import WORLD, spawn_two_ranks  # beside this script (its folder is on sys.path)

from mmm.evaluation.contrastive_module import ContrastiveEvaluatorModule
from mmm.training.configs import ContrastiveModelConfig

RANK0 = 5  # of 8 pairs
FEATURES, SENTENCE, FRAMES = 12, 6, 16


def make_batch() -> dict[str, torch.Tensor]:
    """8 pairs in float64, so that the comparison is exact to rounding."""
    g = torch.Generator().manual_seed(7)
    n = 8
    sentence = torch.randn(n, SENTENCE, generator=g, dtype=torch.float64)
    sentence[6] = sentence[1] * 1.01  # a paraphrase across the ranks: not each other's negative
    mask = torch.zeros(n, 2, dtype=torch.bool)
    mask[:RANK0] = torch.tensor([[True, True], [True, False], [False, False], [True, True], [True, False]])
    return {
        "motion": torch.randn(n, FRAMES, FEATURES, generator=g, dtype=torch.float64),
        "lengths": torch.tensor([16, 12, 16, 8, 16, 12, 16, 8]),
        "sentence": sentence,
        "counterfactual": torch.randn(n, 2, SENTENCE, generator=g, dtype=torch.float64) * mask[..., None],
        "counterfactual_mask": mask,
    }


def rank_part(batch: dict, rank: int) -> dict:
    rows = slice(0, RANK0) if rank == 0 else slice(RANK0, None)
    part = {k: v[rows] for k, v in batch.items()}
    if rank == 1:  # no counterfactuals at all on this rank
        del part["counterfactual"], part["counterfactual_mask"]
    return part


def make_module() -> ContrastiveEvaluatorModule:
    torch.manual_seed(0)
    cfg = ContrastiveModelConfig(embed_dim=8, hidden_dim=8, text_hidden_dim=8, dropout=0.0)
    return ContrastiveEvaluatorModule(FEATURES, SENTENCE, cfg).double()


def work(rank: int, out_dir: str) -> None:
    module = make_module()
    part = rank_part(make_batch(), rank)
    loss, _, _ = module._loss(part, global_negatives=True)
    loss.backward()
    grads = {}
    for name, p in module.named_parameters():
        grad = p.grad.clone()
        dist.all_reduce(grad)
        grads[name] = grad / WORLD  # what DDP's gradient averaging gives every rank
    with torch.no_grad():
        local, _, _ = module._loss(part, global_negatives=False)
    torch.save(
        {"loss": loss.detach(), "local_loss": local, "grads": grads},
        os.path.join(out_dir, f"rank{rank}.pt"),
    )


if __name__ == "__main__":
    spawn_two_ranks(work, sys.argv[1])

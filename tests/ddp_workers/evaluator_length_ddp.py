"""The text-motion evaluator and the length estimator trained on 2 CPU processes over gloo.

Run by tests/test_ddp_evaluator_and_length.py as `python evaluator_length_ddp.py OUT_DIR
evaluator|length`. Random data: the point is that ranks see different batches yet end with the
same weights, and that the validation metrics every rank holds (what best.ckpt is chosen by) are
the whole validation set's, not each rank's half. Each rank saves its weights, first batch,
reduced metrics and its own shard's validation loss (sum and count, measured with the module's
loss on its own batches).
"""

import os
import sys

import lightning as L
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset
from two_ranks import two_process_trainer  # beside this script (its folder is on sys.path)

from mmm.data.resumable import ResumableDataLoader
from mmm.evaluation.contrastive_module import ContrastiveEvaluatorModule
from mmm.generation.length import LengthModelConfig
from mmm.generation.length_module import LengthEstimatorModule
from mmm.optim import OptimConfig
from mmm.training.configs import ContrastiveModelConfig

D, T, DS, DW, WORDS = 12, 24, 16, 8, 5


class RandomPairs(Dataset):
    def __init__(self, n, seed):
        g = torch.Generator().manual_seed(seed)
        self.motion = torch.randn(n, T, D, generator=g)
        self.lengths = torch.randint(8, T + 1, (n,), generator=g)
        self.sentence = torch.randn(n, DS, generator=g)
        self.words = torch.randn(n, WORDS, DW, generator=g)
        self.codes = torch.randint(2, 10, (n,), generator=g)

    def __len__(self):
        return len(self.lengths)

    def __getitem__(self, index):
        return index % len(self)  # the loader tags indices with the epoch (mmm.data.resumable)


def collate(data):
    def fn(indices):
        i = torch.as_tensor(indices)
        return {
            "motion": data.motion[i],
            "lengths": data.lengths[i],
            "sentence": data.sentence[i],
            "words": data.words[i],
            "word_mask": torch.ones(len(i), WORDS, dtype=torch.bool),
            "codes": data.codes[i],
        }

    return fn


def shard_loss(kind, module, batch) -> torch.Tensor:
    """The validation loss of one batch as the module's validation step computes it."""
    if kind == "evaluator":
        return module._loss(batch)[0]
    logits = module._logits(batch)
    return F.cross_entropy(logits.float(), batch["codes"].long().clamp(1, module.model_cfg.max_codes) - 1)


class SaveRankState(L.Callback):
    def __init__(self, out_dir, kind):
        self.out_dir, self.kind, self.first = out_dir, kind, None
        self.shard_sum, self.shard_count = 0.0, 0

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if self.first is None:
            self.first = batch["sentence"].clone()

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        with torch.no_grad():
            n = len(batch["sentence"])
            self.shard_sum += float(shard_loss(self.kind, pl_module, batch)) * n
            self.shard_count += n

    def on_train_end(self, trainer, pl_module):
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}
        torch.save(
            {
                "weights": torch.cat([p.detach().flatten() for p in pl_module.parameters()]),
                "first_batch": self.first,
                "step": trainer.global_step,
                "metrics": metrics,
                "shard_sum": self.shard_sum,
                "shard_count": self.shard_count,
            },
            os.path.join(self.out_dir, f"rank{trainer.global_rank}.pt"),
        )


def main(out_dir, kind):
    L.seed_everything(0)
    train, val = RandomPairs(64, 1), RandomPairs(16, 2)  # 16 val items: 2 batches of 4 per rank
    optim = OptimConfig(lr=1e-3, warmup_steps=0)
    if kind == "evaluator":
        model = ContrastiveModelConfig(embed_dim=16, hidden_dim=8, text_hidden_dim=16, dropout=0.0)
        module = ContrastiveEvaluatorModule(D, DS, model, optim)
    else:
        model = LengthModelConfig(hidden_dim=16, dropout=0.0, max_codes=12, pooling="words")
        module = LengthEstimatorModule(DS, model, optim, word_dim=DW)
    trainer = two_process_trainer(
        12,
        [SaveRankState(out_dir, kind)],
        val_check_interval=12,
        check_val_every_n_epoch=None,
        num_sanity_val_steps=0,
    )
    trainer.fit(
        module,
        ResumableDataLoader(
            train, batch_size=4, shuffle=True, seed=0, collate_fn=collate(train), drop_last=True
        ),
        ResumableDataLoader(val, batch_size=4, shuffle=False, seed=0, collate_fn=collate(val)),
    )


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])

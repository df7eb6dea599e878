"""Stage-2 training on 2 CPU processes over gloo; each rank saves its weights and validation metrics.

Run by tests/test_stage2.py as `python stage2_ddp.py OUT_DIR [parts]`. Random token sequences and
random text embeddings: the point is that ranks see different batches yet end with the same
weights, that validation metrics are reduced across ranks, and that the adherence curve's
figures, measured on rank 0 only, reach every rank's callback_metrics (what best.ckpt can be chosen
by), and that the weights' moving average is the same on every rank. `parts`: the part-aware
transformer on [lower, upper] code pairs (the lower ones its partly masked condition).
"""

import os
import sys

import lightning as L
import torch
from torch.utils.data import Dataset
from two_ranks import two_process_trainer  # beside this script (its folder is on sys.path)

from mmm.callbacks.adherence import AdherenceCurve
from mmm.callbacks.weight_ema import WeightEMA
from mmm.data.resumable import ResumableDataLoader
from mmm.optim import OptimConfig
from mmm.transformer.configs import CorruptionConfig
from mmm.transformer.module import MaskedTransformerModule
from mmm.transformer.network import TransformerConfig

K = 32


class RandomTokens(Dataset):
    def __init__(self, n, seed):
        g = torch.Generator().manual_seed(seed)
        self.lengths = torch.randint(3, 12, (n,), generator=g)
        self.codes = torch.randint(0, K, (n, 12), generator=g)
        self.text = torch.randn(n, 5, 16, generator=g)

    def __len__(self):
        return len(self.lengths)

    def __getitem__(self, index):
        i = index % len(self)
        return i


def collate(data, parts: bool):
    def fn(indices):
        n = len(indices)
        tokens = torch.full((n, 13), K + 1)
        lengths = data.lengths[indices]
        for row, i in enumerate(indices):
            tokens[row, : lengths[row]] = data.codes[i, : lengths[row]]
            tokens[row, lengths[row]] = K
        if parts:  # lower codes: the upper ones reversed within each sequence (END/PAD in place)
            lower = tokens.clone()
            for row in range(n):
                lower[row, : lengths[row]] = tokens[row, : lengths[row]].flip(0)
            tokens = torch.stack((lower, tokens), dim=-1)
        words = data.text[indices]
        return {
            "tokens": tokens,
            "lengths": lengths,
            "sentence": words.mean(1),
            "words": words,
            "word_mask": torch.ones(n, 5, dtype=torch.bool),
        }

    return fn


class RankAdherence(AdherenceCurve):
    """The curve with its measurement replaced by a value that differs per rank, counted."""

    def __init__(self):
        super().__init__(None, None, ".", items=[None], publish=True)
        self.measured = 0

    def _measure(self, pl_module):
        self.measured += 1
        return {"val_adherence/ordered_rate": 0.25 + 0.5 * pl_module.global_rank, "val_adherence/rate": 0.1}


class SaveRankState(L.Callback):
    def __init__(self, out_dir, curve, ema):
        self.out_dir, self.first, self.curve, self.ema = out_dir, None, curve, ema

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if self.first is None:
            self.first = batch["tokens"].clone()

    def on_train_end(self, trainer, pl_module):
        torch.save(
            {
                "weights": torch.cat([p.detach().flatten() for p in pl_module.parameters()]),
                "average": torch.cat(
                    [p.detach().flatten() for p in self.ema._average_model.module.parameters()]
                ),
                "val_loss": float(trainer.callback_metrics["val/loss"]),
                "val_acc": float(trainer.callback_metrics["val/acc_masked"]),
                "first_batch": self.first,
                "step": trainer.global_step,
                "adherence": float(trainer.callback_metrics["val_adherence/ordered_rate"]),
                "measured": self.curve.measured,
            },
            os.path.join(self.out_dir, f"rank{trainer.global_rank}.pt"),
        )


def main(out_dir, parts=False):
    L.seed_everything(0)
    train, val = RandomTokens(64, 1), RandomTokens(10, 2)  # 10 val items: 5 per rank
    module = MaskedTransformerModule(
        torch.randn(K, 8),
        TransformerConfig(
            embed_dim=32, num_heads=2, num_layers=2, num_cross_layers=1, dropout=0.0, max_tokens=13
        ),
        OptimConfig(lr=1e-3, warmup_steps=0),
        CorruptionConfig(cond_drop=0.2),
        sentence_dim=16,
        word_dim=16,
        condition_codebook=torch.randn(K, 4) if parts else None,
    )
    trainer = two_process_trainer(
        15,
        [curve := RankAdherence(), SaveRankState(out_dir, curve, ema := WeightEMA(0.9)), ema],
        val_check_interval=15,
        check_val_every_n_epoch=None,
        num_sanity_val_steps=0,
    )
    trainer.fit(
        module,
        ResumableDataLoader(
            train, batch_size=4, shuffle=True, seed=0, collate_fn=collate(train, parts), drop_last=True
        ),
        ResumableDataLoader(val, batch_size=5, shuffle=False, seed=0, collate_fn=collate(val, parts)),
    )


if __name__ == "__main__":
    main(sys.argv[1], parts=sys.argv[2:] == ["parts"])

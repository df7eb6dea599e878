"""Stage-1 training on 2 CPU processes over gloo; each rank saves its quantizer state at the end.

Run by tests/test_stage1.py as `python stage1_ddp.py DATA_ROOT OUT_DIR [parts|refine]`: Lightning's DDP
launcher re-runs this script for rank 1; `parts` trains the part-aware tokenizer (two codebooks). The collapse
monitor is made to fire on rank 0 only, so both
ranks stopping at the same step shows that the stop decision is reduced across ranks. `refine` runs all
40 steps instead, the last half refining the decoder alone, and also saves each rank's state as the
refinement begins.
"""

import os
import sys

import lightning as L
import torch
from two_ranks import two_process_trainer  # beside this script (its folder is on sys.path)

from mmm.callbacks.codebook import CodebookReset, CollapseMonitor
from mmm.data.configs import DataConfig
from mmm.data.datamodule import TokenizerDataModule
from mmm.optim import OptimConfig
from mmm.tokenizer.configs import TokenizerLossConfig
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.network import TokenizerConfig


class SaveRankState(L.Callback):
    def __init__(self, out_dir):
        self.out_dir, self.first_batch_sum = out_dir, None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if self.first_batch_sum is None:
            self.first_batch_sum = float(batch.sum())
        if trainer.global_step == pl_module.refine_start:
            torch.save(
                {name: value.detach().clone() for name, value in pl_module.tokenizer.state_dict().items()},
                os.path.join(self.out_dir, f"rank{trainer.global_rank}-refine-start.pt"),
            )

    def on_train_end(self, trainer, pl_module):
        quantizers = pl_module.quantizers.values()
        reset = next(c for c in trainer.callbacks if isinstance(c, CodebookReset))
        state = {
            name: torch.cat([getattr(q, name).flatten().float() for q in quantizers])
            for name in ("codebook", "ema_sum", "ema_count", "window_usage")
        }
        torch.save(
            {
                **state,
                "codebooks": len(quantizers),
                "global_step": trainer.global_step,
                "total_reset": reset.total_reset,
                "weights": torch.cat([p.detach().flatten() for p in pl_module.parameters()]),
                "tokenizer": {k: v.detach().clone() for k, v in pl_module.tokenizer.state_dict().items()},
                "first_batch_sum": self.first_batch_sum,
                "at_start": bool(getattr(trainer.train_dataloader.dataset, "at_start", False)),
            },
            os.path.join(self.out_dir, f"rank{trainer.global_rank}.pt"),
        )


def main(data_root, out_dir, parts=False, refine=False):
    L.seed_everything(0)
    rank = int(os.environ.get("LOCAL_RANK", "0"))
    # The refinement as the default runs it: a root-path loss, half its windows at clip starts.
    refine_cfg = {"steps": 20, "path_weight": 0.1, "start_windows": 0.5} if refine else {"steps": 0}
    dm = TokenizerDataModule(
        DataConfig(root=data_root, batch_size=4, synthesize=None),
        seed=0,
        start_windows=refine_cfg.get("start_windows", 0.0),
    )
    dm.prepare_data()
    dm.setup("fit")
    module = TokenizerModule(
        263,
        TokenizerConfig(width=32, num_codes=64, part_aware=parts),
        OptimConfig(warmup_steps=5),
        TokenizerLossConfig(),
        dm.mean,
        dm.std,
        refine=refine_cfg,
    )
    monitor = CollapseMonitor(
        action="stop",
        warmup_steps=24,
        window_steps=4,
        min_active_fraction=2.0 if rank == 0 and not refine else -1.0,
        perplexity_drop=0.0,
        patience=1,
    )
    callbacks = [CodebookReset(3), monitor, SaveRankState(out_dir)]
    trainer = two_process_trainer(40, callbacks, limit_val_batches=0)
    trainer.fit(module, datamodule=dm)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], parts=sys.argv[3:] == ["parts"], refine=sys.argv[3:] == ["refine"])

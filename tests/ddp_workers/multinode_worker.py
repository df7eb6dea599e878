"""One process of a multi-node launch: `mmm train STAGE ...` as the CLI runs it, with probes.

Run by tests/test_multinode.py under torchrun (one torchrun per "node", c10d rendezvous on
127.0.0.1) as `python multinode_worker.py PROBE_DIR STAGE KEY=VALUE ...`. Each rank writes
PROBE_DIR/rank<R>.pt at the end of training: its weights and buffers (codebooks included) and the
sample indices its loader drew in the first epoch; every checkpoint write is appended to
PROBE_DIR/checkpoint-writes.txt with the writing rank.
"""

import os
import sys

import lightning as L
import torch

from mmm.cli import main as cli_main
from mmm.data.resumable import ShardedRandomSampler
from mmm.training import checkpoint_io, stage1, stage2

PROBE_DIR = sys.argv[1]
first_epoch: list[int] = []


def rank() -> int:
    return int(os.environ.get("RANK", "0"))


class RankProbe(L.Callback):
    def on_train_end(self, trainer, pl_module):
        state = {k: v.detach().float().flatten() for k, v in pl_module.state_dict().items()}
        torch.save(
            {"state": state, "first_epoch": first_epoch, "global_step": trainer.global_step},
            os.path.join(PROBE_DIR, f"rank{trainer.global_rank}.pt"),
        )


def record_first_epoch(indices_of):
    def _indices(self):
        indices = indices_of(self)
        if self.epoch == 0 and not first_epoch and self.shuffle:  # the training loader's epoch 0
            first_epoch.extend(indices)
        return indices

    return _indices


def record_writes(save):
    def save_checkpoint(self, checkpoint, path, storage_options=None):
        with open(os.path.join(PROBE_DIR, "checkpoint-writes.txt"), "a") as f:
            f.write(f"{rank()} {path}\n")
        return save(self, checkpoint, path, storage_options)

    return save_checkpoint


def with_probe(fit):
    def tracked_fit(run, cfg, module, target, callbacks, **kwargs):
        return fit(run, cfg, module, target, [*callbacks, RankProbe()], **kwargs)

    return tracked_fit


ShardedRandomSampler._indices = record_first_epoch(ShardedRandomSampler._indices)
save = checkpoint_io.AtomicCheckpointIO.save_checkpoint
checkpoint_io.AtomicCheckpointIO.save_checkpoint = record_writes(save)
stage1.tracked_fit = with_probe(stage1.tracked_fit)
stage2.tracked_fit = with_probe(stage2.tracked_fit)

if __name__ == "__main__":
    sys.exit(cli_main(["train", *sys.argv[2:]]))

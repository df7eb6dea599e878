"""The Trainer of the DDP workers here: 2 CPU processes over gloo with the package's DDP strategy,
no logger, checkpoints or progress bar, and loaders that shard themselves (mmm.data.resumable)."""

import lightning as L

from mmm.training.common import build_strategy
from mmm.training.configs import TrainerConfig


def two_process_trainer(max_steps: int, callbacks: list, **options) -> L.Trainer:
    return L.Trainer(
        accelerator="cpu",
        devices=2,
        strategy=build_strategy(TrainerConfig(strategy="ddp", process_group_backend="gloo")),
        max_steps=max_steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        use_distributed_sampler=False,
        callbacks=callbacks,
        **options,
    )

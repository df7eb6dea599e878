"""Prompt adherence as a learning curve of stage 2: at each validation, a fixed set of labelled
validation captions generated at their true lengths and checked by the synthetic dataset's
checker (strict and order-aware, overall and per group: single actions, compositions, counts),
logged to MLflow with the step. A run then shows when what the model follows stops improving."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import torch

from mmm.evaluation.adherence import adherence_metrics, prompt_adherence
from mmm.generation.model import TextToMotion


class AdherenceCurve(L.Callback):
    """Logs `val_adherence/*` (see adherence_metrics) at each validation, computed on rank 0 only.
    `items` are MotionItems of a labelled dataset at `root`; whole-body models only.

    publish: also hand the figures to every rank's `trainer.callback_metrics` (broadcast from rank
    0, so every rank's checkpoint callback takes the same decision), so `best.ckpt` can be chosen
    by one of them (callbacks.checkpoint.monitor=val_adherence/ordered_rate). Without it the other
    ranks do not wait: nothing here is collective."""

    def __init__(
        self, tokenizer, text_encoder, root: str | Path, items: list, seed: int = 0, publish: bool = False
    ):
        self.tokenizer, self.text_encoder = tokenizer, text_encoder
        self.root, self.items, self.seed, self.publish = Path(root), list(items), seed, publish

    def _measure(self, pl_module) -> dict[str, float]:
        training = pl_module.transformer.training
        model = TextToMotion(
            self.tokenizer, pl_module.transformer, self.text_encoder, {}, device=pl_module.device
        )
        try:
            result = prompt_adherence(model, self.root, self.items, seed=self.seed)
        finally:
            pl_module.transformer.train(training)
        return adherence_metrics(result, "val_adherence")

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if trainer.sanity_checking or not self.items:
            return
        if not self.publish and (not trainer.is_global_zero or not trainer.loggers):
            return
        metrics = self._measure(pl_module) if trainer.is_global_zero else None
        if self.publish:
            metrics = trainer.strategy.broadcast(metrics, src=0)
            trainer.callback_metrics.update({k: torch.tensor(v) for k, v in metrics.items()})
        if trainer.is_global_zero:
            for logger in trainer.loggers:
                logger.log_metrics(metrics, step=trainer.global_step)

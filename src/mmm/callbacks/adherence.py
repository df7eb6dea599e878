"""Prompt adherence as a learning curve of stage 2: at each validation, a fixed set of labelled
validation captions generated at their true lengths and checked by the synthetic dataset's
checker (strict and order-aware, overall and per group: single actions, compositions, counts),
logged to MLflow with the step. A run then shows when what the model follows stops improving."""

from __future__ import annotations

from pathlib import Path

import lightning as L

from mmm.evaluation.adherence import adherence_metrics, prompt_adherence
from mmm.generation.model import TextToMotion


class AdherenceCurve(L.Callback):
    """Logs `val_adherence/*` (see adherence_metrics) at each validation, computed on rank 0 only
    (the other ranks do not wait for it: nothing here is collective). `items` are MotionItems of
    a labelled dataset at `root`; whole-body models only."""

    def __init__(self, tokenizer, text_encoder, root: str | Path, items: list, seed: int = 0):
        self.tokenizer, self.text_encoder = tokenizer, text_encoder
        self.root, self.items, self.seed = Path(root), list(items), seed

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if not trainer.is_global_zero or trainer.sanity_checking or not self.items or not trainer.loggers:
            return
        training = pl_module.transformer.training
        model = TextToMotion(
            self.tokenizer, pl_module.transformer, self.text_encoder, {}, device=pl_module.device
        )
        try:
            result = prompt_adherence(model, self.root, self.items, seed=self.seed)
        finally:
            pl_module.transformer.train(training)
        metrics = adherence_metrics(result, "val_adherence")
        for logger in trainer.loggers:
            logger.log_metrics(metrics, step=trainer.global_step)

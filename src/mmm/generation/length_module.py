"""`LengthEstimatorModule`: training of the length estimator (mmm.generation.length).

It trains a LengthEstimator on (sentence embedding, token count) pairs with cross-entropy and
reports, on validation, the exact accuracy, the accuracy within ±1 and ±2 tokens and the mean
absolute error in frames of the most likely count (and the error of the distribution's median).
Its hyper-parameters are plain dicts, so checkpoints load with torch.load(weights_only=True); the
network sits under `estimator.`, what `load_length_estimator(path)` reads back.
"""

from __future__ import annotations

from dataclasses import asdict

import lightning as L
import torch
import torch.nn as nn
import torch.nn.functional as F
from torchmetrics import MeanMetric

from mmm.config import as_config
from mmm.generation.length import LengthEstimator, LengthModelConfig, length_metrics, median_count
from mmm.optim import OptimConfig, build_optimizer
from mmm.step_logging import logged_step


class LengthEstimatorModule(L.LightningModule):
    """Trains a LengthEstimator on batches {"sentence" (B, Ds) float, "codes" (B,) int token counts},
    plus "words" (B, L, Dw) and "word_mask" (B, L) for an estimator with pooling "words" (word_dim:
    the text encoder's per-token feature size).

    text_encoder / stage1: identities recorded with the model (the estimator is only valid with the
    text encoder it was trained on; stage 1 defines what a token count is).
    """

    def __init__(
        self,
        sentence_dim: int,
        model: LengthModelConfig | dict | None = None,
        optim: OptimConfig | dict | None = None,
        label_smoothing: float = 0.0,
        text_encoder: dict | None = None,
        stage1: dict | None = None,
        word_dim: int | None = None,
    ):
        super().__init__()
        model = as_config(LengthModelConfig, model) if model is not None else LengthModelConfig()
        optim = as_config(OptimConfig, optim) if optim is not None else OptimConfig(lr=1e-3, warmup_steps=0)
        self.save_hyperparameters(
            {
                "sentence_dim": int(sentence_dim),
                "word_dim": None if word_dim is None else int(word_dim),
                "model": asdict(model),
                "optim": asdict(optim),
                "label_smoothing": float(label_smoothing),
                "text_encoder": dict(text_encoder or {}),
                "stage1": dict(stage1 or {}),
            },
            logger=False,
        )
        self.model_cfg, self.optim_cfg, self.label_smoothing = model, optim, float(label_smoothing)
        self.estimator = LengthEstimator(sentence_dim, model, word_dim)
        self.val_metrics = nn.ModuleDict(
            {
                name: MeanMetric()
                for name in ("loss", "acc", "acc_within1", "acc_within2", "mae_frames", "mae_frames_median")
            }
        )

    def _logits(self, batch: dict) -> torch.Tensor:
        return self.estimator.logits(batch["sentence"], batch.get("words"), batch.get("word_mask"))

    def _loss(self, logits: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        target = codes.long().clamp(1, self.model_cfg.max_codes) - 1
        return F.cross_entropy(logits.float(), target, label_smoothing=self.label_smoothing)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        logits = self._logits(batch)
        loss = self._loss(logits, batch["codes"])
        if not logged_step(self):
            return loss
        hits = length_metrics(logits.argmax(-1) + 1, batch["codes"], self.model_cfg.unit_length)
        self.log_dict(
            {"train/loss": loss, "train/acc_within1": hits["acc_within1"].mean()},
            on_step=True,
            on_epoch=False,
        )
        self.log("loss", loss, prog_bar=True, logger=False)
        return loss

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        logits = self._logits(batch)
        n = len(batch["codes"])
        self.val_metrics["loss"].update(
            F.cross_entropy(logits.float(), batch["codes"].long().clamp(1, self.model_cfg.max_codes) - 1),
            weight=n,
        )
        for name, values in length_metrics(
            logits.argmax(-1) + 1, batch["codes"], self.model_cfg.unit_length
        ).items():
            self.val_metrics[name].update(values)
        median = length_metrics(median_count(logits), batch["codes"], self.model_cfg.unit_length)
        self.val_metrics["mae_frames_median"].update(median["mae_frames"])

    def on_validation_epoch_end(self) -> None:
        values = {f"val/{name}": metric.compute() for name, metric in self.val_metrics.items()}
        self.log_dict(values, prog_bar=False)
        self.log("val_within1", values["val/acc_within1"], prog_bar=True, logger=False)
        for metric in self.val_metrics.values():
            metric.reset()

    def configure_optimizers(self):
        return build_optimizer(
            self.estimator.parameters(), self.optim_cfg, total_steps=self.trainer.max_steps
        )

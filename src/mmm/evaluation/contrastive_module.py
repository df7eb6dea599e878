"""`ContrastiveEvaluatorModule`: training of the contrastive text-motion evaluator
(mmm.evaluation.contrastive), and its loss.

A symmetric InfoNCE loss over the batch with the evaluator's learnable temperature; pairs whose
frozen sentence embeddings are nearly identical (cosine >= `false_negative_threshold`) can be left
out of each other's negatives. Under DDP the training loss contrasts the pairs of every rank
(`global_batch`, `loss.global_negatives`), so its value and gradient are those of one process on
the whole batch, not of each rank's share of it. The module validates with the loss and text->motion /
motion->text top-1/top-5 within batches, and keeps plain-dict hyper-parameters, so checkpoints
load with torch.load(weights_only=True); the network sits under `evaluator.`, what
`load_contrastive_evaluator(path)` reads back.
"""

from __future__ import annotations

from dataclasses import asdict

import lightning as L
import numpy as np
import torch
import torch.distributed as dist
import torch.nn as nn
import torch.nn.functional as F
from torchmetrics import MeanMetric

from mmm.config import as_config
from mmm.evaluation.contrastive import ContrastiveEvaluator, matching_ranks
from mmm.optim import OptimConfig, build_optimizer
from mmm.step_logging import logged_step
from mmm.training.configs import ContrastiveLossConfig, ContrastiveModelConfig


def false_negative_mask(sentences: torch.Tensor, threshold: float | None) -> torch.Tensor | None:
    """(B, Ds) frozen sentence embeddings -> (B, B) bool, True where pair (i, j), i != j, is too
    alike (cosine >= threshold) to serve as a negative; None when no threshold is set."""
    if threshold is None:
        return None
    unit = F.normalize(sentences.float(), dim=-1)
    alike = unit @ unit.T >= threshold
    return alike & ~torch.eye(len(unit), dtype=torch.bool, device=unit.device)


def info_nce_loss(
    text: torch.Tensor,
    motion: torch.Tensor,
    logit_scale: torch.Tensor | float,
    exclude: torch.Tensor | None = None,
    hard_text: torch.Tensor | None = None,
    hard_mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Symmetric InfoNCE: text i's positive is motion i and vice versa, the other rows negatives.

    text, motion: (B, E), L2-normalized here; logits = scale * cosine (B, B). The loss is the mean
    of the text->motion cross-entropy (rows) and the motion->text one (columns). `exclude` (B, B)
    bool removes off-diagonal pairs from the negatives (the diagonal is always kept).
    hard_text (B, K, E) with hard_mask (B, K) bool (True: a real one): captions that only motion i
    must rank below its own (its caption's counterfactuals), added to motion i's candidates.
    """
    t, m = F.normalize(text.float(), dim=-1), F.normalize(motion.float(), dim=-1)
    scale = torch.as_tensor(logit_scale, dtype=t.dtype, device=t.device)
    logits = scale * (t @ m.T)
    if exclude is not None:
        exclude = exclude & ~torch.eye(len(t), dtype=torch.bool, device=t.device)
        logits = logits.masked_fill(exclude, float("-inf"))
    target = torch.arange(len(t), device=t.device)
    motion_to_text = logits.T
    if hard_text is not None and hard_text.shape[1] > 0:
        hard = scale * torch.einsum("be,bke->bk", m, F.normalize(hard_text.float(), dim=-1))
        hard = hard.masked_fill(~hard_mask, float("-inf"))
        motion_to_text = torch.cat([motion_to_text, hard], dim=1)
    return 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(motion_to_text, target))


class _GatherRows(torch.autograd.Function):
    """Every rank's (n, ...) rows, concatenated in rank order; all ranks pass the same shape. The
    gradient of the result is summed over the ranks (gloo has no reduce-scatter) and each rank
    keeps its own rows' part."""

    @staticmethod
    def forward(ctx, rows: torch.Tensor) -> torch.Tensor:
        parts = [torch.empty_like(rows) for _ in range(dist.get_world_size())]
        dist.all_gather(parts, rows.contiguous())
        ctx.rows = len(rows)
        return torch.cat(parts)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        grad = grad.contiguous().clone()
        dist.all_reduce(grad)
        start = dist.get_rank() * ctx.rows
        return grad[start : start + ctx.rows]


def global_batch(
    text: torch.Tensor,
    motion: torch.Tensor,
    sentence: torch.Tensor,
    hard: torch.Tensor | None = None,
    hard_mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """The pairs of every rank, in rank order: text, motion (B, E), sentence (B, Ds), the hard
    negatives (B, K, E) and hard_mask (B, K), with gradients to each rank's own rows. Ranks may
    hold different B and K (a short last batch, captions with fewer counterfactuals): rows and
    negatives are padded for the exchange and the padding dropped. Outside DDP: the inputs.

    Everything travels in one tensor, so every rank makes the same collectives in the backward
    pass too (one all_reduce), whatever its own batch needs a gradient for."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return text, motion, sentence, hard, hard_mask
    (n, e), k = text.shape, 0 if hard is None else hard.shape[1]
    sizes = [torch.zeros(2, dtype=torch.long, device=text.device) for _ in range(dist.get_world_size())]
    dist.all_gather(sizes, torch.tensor([n, k], device=text.device))
    rows, cols = (int(v) for v in torch.stack(sizes).max(0).values)
    if hard is None:
        hard, hard_mask = text.new_zeros(n, 0, e), torch.zeros(n, 0, dtype=torch.bool, device=text.device)
    packed = torch.cat(
        [
            text,
            motion,
            sentence.to(text.dtype),
            F.pad(hard, (0, 0, 0, cols - k)).flatten(1),
            F.pad(hard_mask.to(text.dtype), (0, cols - k)),
        ],
        dim=1,
    )
    keep = torch.cat([torch.arange(rows) < int(size[0]) for size in sizes]).to(text.device)
    packed = _GatherRows.apply(F.pad(packed, (0, 0, 0, rows - n)))[keep]
    text, motion, sentence, hard, mask = packed.split([e, e, sentence.shape[1], cols * e, cols], dim=1)
    if cols == 0:
        return text, motion, sentence, None, None
    return text, motion, sentence, hard.unflatten(1, (cols, e)), mask > 0.5


class ContrastiveEvaluatorModule(L.LightningModule):
    """Trains a ContrastiveEvaluator on {"motion" (B, T, D) normalized, "lengths" (B,), "sentence" (B, Ds)},
    with hard negatives when the batch holds "counterfactual" (B, K, Ds) and "counterfactual_mask" (B, K).

    text_encoder: the frozen encoder whose sentence embeddings it reads ({"name", "identity", ...});
    data: what it was trained on ({"name", "root", "fingerprint"}). Both go into the checkpoint.
    Validation batches should hold `retrieval_batch` pairs (32): top-k are within the batch.
    """

    def __init__(
        self,
        feature_dim: int,
        sentence_dim: int,
        model: ContrastiveModelConfig | dict | None = None,
        optim: OptimConfig | dict | None = None,
        loss: ContrastiveLossConfig | dict | None = None,
        mean: np.ndarray | torch.Tensor | None = None,
        std: np.ndarray | torch.Tensor | None = None,
        text_encoder: dict | None = None,
        data: dict | None = None,
    ):
        super().__init__()
        model = as_config(ContrastiveModelConfig, model) if model is not None else ContrastiveModelConfig()
        optim = (
            as_config(OptimConfig, optim)
            if optim is not None
            else OptimConfig(lr=1e-3, weight_decay=1e-2, warmup_steps=0)
        )
        loss = as_config(ContrastiveLossConfig, loss) if loss is not None else ContrastiveLossConfig()
        # Tensors first, and never into the hyper-parameters (plain dicts: weights_only loads).
        mean = None if mean is None else torch.as_tensor(mean, dtype=torch.float32)
        std = None if std is None else torch.as_tensor(std, dtype=torch.float32)
        self.save_hyperparameters(
            {
                "feature_dim": int(feature_dim),
                "sentence_dim": int(sentence_dim),
                "model": asdict(model),
                "optim": asdict(optim),
                "loss": asdict(loss),
                "text_encoder": dict(text_encoder or {}),
                "data": dict(data or {}),
            },
            logger=False,
        )
        self.model_cfg, self.optim_cfg, self.loss_cfg = model, optim, loss
        self.evaluator = ContrastiveEvaluator(feature_dim, sentence_dim, model, mean, std)
        self.val_metrics = nn.ModuleDict(
            {name: MeanMetric() for name in ("loss", "t2m_top1", "t2m_top5", "m2t_top1", "m2t_top5")}
        )

    def _loss(self, batch: dict, global_negatives: bool = False) -> tuple[torch.Tensor, ...]:
        """(loss, text, motion): the rank's own embeddings (B, E); with `global_negatives`, the loss
        over the pairs of every rank (global_batch)."""
        ev = self.evaluator
        motion = ev.motion_features(batch["motion"], batch["lengths"])
        text = ev.text_features(batch["sentence"])
        hard, hard_mask = batch.get("counterfactual"), batch.get("counterfactual_mask")
        if hard is not None:
            hard = ev.text_features(hard.flatten(0, 1)).unflatten(0, hard.shape[:2])
        pairs = (text, motion, batch["sentence"], hard, hard_mask)
        if global_negatives:
            pairs = global_batch(*pairs)
        all_text, all_motion, sentence, hard, hard_mask = pairs
        exclude = false_negative_mask(sentence, self.loss_cfg.false_negative_threshold)
        loss = info_nce_loss(all_text, all_motion, ev.scale(), exclude, hard, hard_mask)
        return loss, text, motion

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        loss, text, motion = self._loss(batch, self.loss_cfg.global_negatives)
        if not logged_step(self):  # the retrieval ranks below only go to the loggers
            return loss
        t2m, _ = matching_ranks(F.normalize(text.detach(), dim=-1), F.normalize(motion.detach(), dim=-1))
        self.log_dict(
            {
                "train/loss": loss,
                "train/temperature": 1.0 / self.evaluator.scale().detach(),
                "train/t2m_top1": (t2m == 0).float().mean(),
            },
            on_step=True,
            on_epoch=False,
            batch_size=len(t2m),
        )
        self.log("loss", loss, prog_bar=True, logger=False, batch_size=len(t2m))
        return loss

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        loss, text, motion = self._loss(batch)
        t2m, m2t = matching_ranks(F.normalize(text, dim=-1), F.normalize(motion, dim=-1))
        self.val_metrics["loss"].update(loss, weight=len(t2m))
        for k in (1, 5):
            self.val_metrics[f"t2m_top{k}"].update((t2m < k).float())
            self.val_metrics[f"m2t_top{k}"].update((m2t < k).float())

    def on_validation_epoch_end(self) -> None:
        values = {f"val/{name}": metric.compute() for name, metric in self.val_metrics.items()}
        self.log_dict(values)
        self.log("val_t2m_top1", values["val/t2m_top1"], prog_bar=True, logger=False)
        for metric in self.val_metrics.values():
            metric.reset()

    def configure_optimizers(self):
        # Weight decay on the weight matrices only: none on biases, norms and the logit scale.
        return build_optimizer(
            self.evaluator.parameters(),
            self.optim_cfg,
            decay_matrices_only=True,
            total_steps=self.trainer.max_steps,
        )

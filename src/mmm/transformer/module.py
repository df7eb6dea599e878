"""`MaskedTransformerModule`: stage-2 training of the MaskedMotionTransformer on cached tokens."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import lightning as L
import torch
import torch.nn.functional as F
from torchmetrics import MeanMetric

from mmm.config import as_config
from mmm.optim import OptimConfig, build_optimizer
from mmm.step_logging import logged_step
from mmm.transformer.configs import CorruptionConfig
from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig
from mmm.transformer.schedules import TRAINING_SCHEDULES


@dataclass
class Corrupted:
    inputs: torch.Tensor  # (B, M) tokens given to the model
    masked: torch.Tensor  # (B, M) bool: replaced by MASK
    replaced: torch.Tensor  # (B, M) bool: replaced by a random code (and not masked)
    real: torch.Tensor  # (B, M) bool: code positions (before END)


def random_positions(scores: torch.Tensor, real: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """(B, M) bool: in each row, the `count` (B,) real positions with the smallest `scores` (B, M)
    (uniform random scores in [0, 1) make it a uniform choice)."""
    scores = torch.where(real, scores, torch.full_like(scores, 2.0))
    return scores.argsort(dim=1).argsort(dim=1) < count[:, None]


def corrupt(
    tokens: torch.Tensor,
    lengths: torch.Tensor,
    num_codes: int,
    cfg: CorruptionConfig,
    generator: torch.Generator | None = None,
) -> Corrupted:
    """Corrupt (B, M) token sequences as in training: random replacement, then masking.

    Each sequence masks round(r * L) of its L real positions (at least 1), chosen uniformly;
    END and PAD are never touched.
    """
    B, M = tokens.shape
    device = tokens.device
    positions = torch.arange(M, device=device)
    real = positions[None] < lengths[:, None]

    def rand(*shape):
        return torch.rand(*shape, generator=generator, device=device)

    replace = (rand(B, M) >= cfg.pkeep) & real
    random_codes = torch.randint(0, num_codes, (B, M), generator=generator, device=device)
    inputs = torch.where(replace, random_codes, tokens)
    u = rand(B)
    ratio = TRAINING_SCHEDULES[cfg.mask_schedule](u)
    count = torch.round(ratio * lengths).clamp(min=1).minimum(lengths).long()
    masked = random_positions(rand(B, M), real, count)
    inputs = torch.where(masked, torch.full_like(inputs, num_codes + 2), inputs)
    return Corrupted(inputs, masked, replace & ~masked, real)


def mask_condition(
    lower: torch.Tensor,
    lengths: torch.Tensor,
    max_share: float,
    mask_id: int,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Lower-body condition codes (B, M) with a share ~ U(0, max_share) of each sequence's real
    positions replaced by MASK (chosen uniformly), so the model learns every strength of the
    lower-body constraint, from all of it to none."""
    B, M = lower.shape
    device = lower.device
    real = torch.arange(M, device=device)[None] < lengths[:, None]
    share = torch.rand(B, generator=generator, device=device) * max_share
    count = torch.round(share * lengths).long()
    hidden = random_positions(torch.rand(B, M, generator=generator, device=device), real, count)
    return torch.where(hidden, torch.full_like(lower, mask_id), lower)


def sequence_mean(values: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Mean over each sequence's weighted positions, then over the batch (B, M) -> ()."""
    weight = weight.to(values.dtype)
    per_sequence = (values * weight).sum(1) / weight.sum(1).clamp_min(1.0)
    has_any = weight.sum(1) > 0
    return per_sequence[has_any].mean() if bool(has_any.any()) else values.sum() * 0.0


def stage2_codebooks(tokenizer) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(codebook the transformer predicts, condition codebook or None) of a stage-1 TokenizerModule:
    a part-aware tokenizer gives (upper body, lower body), a whole-body one (its codebook, None)."""
    net = tokenizer.tokenizer
    if getattr(net, "part_aware", False):
        return net.upper.codebook.detach().cpu(), net.lower.codebook.detach().cpu()
    return net.codebook.detach().cpu(), None


class MaskedTransformerModule(L.LightningModule):
    """Trains the masked transformer on batches from TokenBatchCollator.

    codebook: (K, C) of the stage-1 model; stage1/text_encoder: identities recorded with the model.
    condition_codebook: the lower-body codebook of a part-aware stage-1 model (then `codebook` is
    its upper-body one, batches hold (B, M, 2) tokens [lower, upper], and the model learns upper
    codes given a partly masked lower body).
    """

    def __init__(
        self,
        codebook: torch.Tensor,
        model: TransformerConfig | dict,
        optim: OptimConfig | dict,
        corruption: CorruptionConfig | dict,
        sentence_dim: int,
        word_dim: int,
        stage1: dict | None = None,
        text_encoder: dict | None = None,
        condition_codebook: torch.Tensor | None = None,
    ):
        super().__init__()
        model, optim, corruption = (
            as_config(TransformerConfig, model),
            as_config(OptimConfig, optim),
            as_config(CorruptionConfig, corruption),
        )
        codebook = torch.as_tensor(codebook, dtype=torch.float32)
        condition_codebook = (
            None if condition_codebook is None else torch.as_tensor(condition_codebook, dtype=torch.float32)
        )
        self.save_hyperparameters(
            {
                "codebook_shape": list(codebook.shape),
                "model": asdict(model),
                "optim": asdict(optim),
                "corruption": asdict(corruption),
                "sentence_dim": sentence_dim,
                "word_dim": word_dim,
                "stage1": stage1 or {},
                "text_encoder": text_encoder or {},
                "condition_codebook_shape": None
                if condition_codebook is None
                else list(condition_codebook.shape),
            },
            logger=False,
        )
        self.model_cfg, self.optim_cfg, self.corruption_cfg = model, optim, corruption
        self.transformer = MaskedMotionTransformer(
            codebook, model, sentence_dim, word_dim, condition_codebook
        )
        self.num_codes = codebook.shape[0]
        self.val_loss, self.val_acc_masked, self.val_acc_unmasked = MeanMetric(), MeanMetric(), MeanMetric()
        self.preview_batch: dict | None = None  # first validation batch, for generation previews

    def targets_and_condition(
        self, batch: dict, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(codes to predict (B, M), lower-body condition (B, M) or None) of a batch."""
        tokens = batch["tokens"]
        if not self.transformer.part_aware:
            return tokens, None
        if tokens.dim() != 3:
            raise ValueError(
                "a part-aware transformer trains on (B, M, 2) tokens of a part-aware stage-1 model, got "
                f"{tuple(tokens.shape)}"
            )
        condition = mask_condition(
            tokens[..., 0],
            batch["lengths"],
            self.corruption_cfg.lower_mask,
            self.transformer.condition.mask_id,
            generator,
        )
        return tokens[..., 1], condition

    def loss(self, logits: torch.Tensor, targets: torch.Tensor, corrupted: Corrupted) -> torch.Tensor:
        """The cross-entropy of logits (B, M, K) against targets (B, M), averaged over each
        sequence's masked (loss_on: masked) or real positions, then over the batch."""
        ce = F.cross_entropy(
            logits.transpose(1, 2), targets.clamp(max=self.num_codes - 1), reduction="none"
        )  # (B, M); END/PAD are never targets
        weight = corrupted.masked if self.corruption_cfg.loss_on == "masked" else corrupted.real
        return sequence_mean(ce, weight)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        targets, condition = self.targets_and_condition(batch)
        corrupted = corrupt(targets, batch["lengths"], self.num_codes, self.corruption_cfg)
        drop = (
            torch.rand(len(batch["lengths"]), device=self.device) < self.corruption_cfg.cond_drop
            if self.corruption_cfg.cond_drop > 0
            else None
        )
        logits = self.transformer(
            corrupted.inputs, batch["sentence"], batch["words"], batch["word_mask"], drop, condition
        )
        loss = self.loss(logits, targets, corrupted)
        if not logged_step(self):  # the accuracies below only go to the loggers
            return loss
        correct = logits.argmax(-1) == targets
        unmasked = corrupted.real & ~corrupted.masked
        self.log_dict(
            {
                "train/loss": loss,
                "train/acc_masked": sequence_mean(correct.float(), corrupted.masked),
                "train/acc_unmasked": sequence_mean(correct.float(), unmasked),
                "train/mask_fraction": corrupted.masked.sum() / corrupted.real.sum(),
            },
            on_step=True,
            on_epoch=False,
        )
        self.log("loss", loss, prog_bar=True, logger=False)
        return loss

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        # The same corruption at every validation: comparable numbers across a run.
        generator = torch.Generator(device=batch["tokens"].device).manual_seed(1234 + batch_idx)
        targets, condition = self.targets_and_condition(batch, generator)
        corrupted = corrupt(targets, batch["lengths"], self.num_codes, self.corruption_cfg, generator)
        logits = self.transformer(
            corrupted.inputs, batch["sentence"], batch["words"], batch["word_mask"], None, condition
        )
        loss, correct = self.loss(logits, targets, corrupted), logits.argmax(-1) == targets
        unmasked = corrupted.real & ~corrupted.masked
        self.val_loss.update(loss, weight=len(batch["lengths"]))
        self.val_acc_masked.update(correct[corrupted.masked].float().mean(), weight=corrupted.masked.sum())
        if bool(unmasked.any()):
            self.val_acc_unmasked.update(correct[unmasked].float().mean(), weight=unmasked.sum())
        if batch_idx == 0:
            self.preview_batch = {
                k: (v.detach().cpu() if torch.is_tensor(v) else v) for k, v in batch.items()
            }

    def on_validation_epoch_end(self) -> None:
        self.log_dict(
            {
                "val/loss": self.val_loss.compute(),
                "val/acc_masked": self.val_acc_masked.compute(),
                "val/acc_unmasked": self.val_acc_unmasked.compute(),
            },
            prog_bar=True,
        )
        for metric in (self.val_loss, self.val_acc_masked, self.val_acc_unmasked):
            metric.reset()

    def configure_optimizers(self):
        return build_optimizer(
            self.transformer.parameters(),
            self.optim_cfg,
            foreach=True,
            total_steps=self.trainer.max_steps,
        )

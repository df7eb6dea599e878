"""`TokenizerModule`: stage-1 training of the MotionTokenizer (losses, optimizer, validation).

With `model.tokenizer.part_aware=true` it trains a PartAwareTokenizer (two codebooks) instead;
codebook metrics are then logged per codebook (`codebook/lower/perplexity`, ...).
"""

from __future__ import annotations

from dataclasses import asdict

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torchmetrics import MeanMetric

from mmm.config import as_config
from mmm.motion.features import FeatureLayout, recover_from_ric, recover_root_rot_pos
from mmm.motion.skeleton import skeleton_for
from mmm.optim import OptimConfig, build_optimizer
from mmm.step_logging import logged_step
from mmm.tokenizer.configs import DecoderRefineConfig, TokenizerLossConfig
from mmm.tokenizer.network import MotionTokenizer, TokenizerConfig
from mmm.tokenizer.parts import PartAwareTokenizer
from mmm.tokenizer.quantizer import EMAQuantizer, metric_name
from mmm.tokenizer.search import CodeSearchConfig, search_codes


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of values (B, T, ...) over positions where mask (B, T) is true."""
    mask = mask.to(values.dtype).view(mask.shape + (1,) * (values.dim() - 2))
    return (values * mask).sum() / (mask.sum() * values[0, 0].numel()).clamp_min(1.0)


class TokenizerModule(L.LightningModule):
    """Trains a MotionTokenizer (or a PartAwareTokenizer) on normalized windows (B, T, D);
    validates on whole clips.

    mean/std: the dataset statistics (D,), kept as buffers so a checkpoint can denormalize.
    """

    def __init__(
        self,
        feature_dim: int,
        model: TokenizerConfig | dict,
        optim: OptimConfig | dict,
        loss: TokenizerLossConfig | dict,
        mean: np.ndarray | torch.Tensor | None = None,
        std: np.ndarray | torch.Tensor | None = None,
        refine: DecoderRefineConfig | dict | None = None,
        encode: CodeSearchConfig | dict | None = None,
    ):
        super().__init__()
        model, optim, loss, refine, encode = (
            as_config(TokenizerConfig, model),
            as_config(OptimConfig, optim),
            as_config(TokenizerLossConfig, loss),
            as_config(DecoderRefineConfig, refine or {}),
            as_config(CodeSearchConfig, encode or {}),
        )
        # Tensors before save_hyperparameters, which compares its argument with every init
        # argument (a numpy array cannot be compared with a dict).
        mean = torch.as_tensor(mean if mean is not None else np.zeros(feature_dim), dtype=torch.float32)
        std = torch.as_tensor(std if std is not None else np.ones(feature_dim), dtype=torch.float32)
        # Plain dicts, so checkpoints load with torch.load(weights_only=True).
        self.save_hyperparameters(
            {
                "feature_dim": feature_dim,
                "model": asdict(model),
                "optim": asdict(optim),
                "loss": asdict(loss),
                "refine": asdict(refine),
                "encode": asdict(encode),
            },
            logger=False,
        )
        self.model_cfg, self.optim_cfg, self.loss_cfg, self.refine_cfg = model, optim, loss, refine
        # How `encode` tokenizes a known motion (mmm.tokenizer.search); `auto` resolved for this machine.
        self.encode_cfg = encode.resolved()
        self.tokenizer = (
            PartAwareTokenizer(feature_dim, model)
            if model.part_aware
            else MotionTokenizer(feature_dim, model)
        )
        self.skeleton = skeleton_for(feature_dim)
        self.layout = FeatureLayout(self.skeleton.num_joints)
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)
        self.val_recon = MeanMetric()
        self.val_mpjpe = MeanMetric()  # each pose aligned by its pelvis (the standard protocol)
        self.val_mpjpe_global = MeanMetric()  # recovered root path included
        self.last_perplexities: dict[str, float] = {}  # of the last training batch, keyed like `quantizers`
        self.preview_batch: dict | None = None  # first validation batch with reconstructions

    @property
    def quantizers(self) -> dict[str, EMAQuantizer]:
        """The codebooks by name: {"": q} for the plain tokenizer, {"lower": q, "upper": q} part-aware."""
        return self.tokenizer.quantizers

    @property
    def quantizer(self) -> EMAQuantizer:
        """The one codebook of the plain tokenizer."""
        quantizers = self.quantizers
        if len(quantizers) != 1:
            # Not AttributeError: nn.Module would swallow it and report a missing attribute.
            raise TypeError(
                f"this tokenizer has {len(quantizers)} codebooks ({', '.join(quantizers)}): use `quantizers`"
            )
        return quantizers[""]

    @property
    def refine_start(self) -> int | None:
        """The first optimizer step of the decoder refinement: the fit's last `refine.steps`
        (None: no refinement, or no trainer)."""
        steps = self.refine_cfg.steps
        return self.trainer.max_steps - steps if steps > 0 and self._trainer is not None else None

    @property
    def refining(self) -> bool:
        """Whether this step trains the decoder alone (the codebook callbacks then stand still)."""
        start = self.refine_start
        return start is not None and self.global_step >= start

    def losses(
        self,
        recon: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor | None = None,
        root_weight: float | None = None,
    ) -> dict[str, torch.Tensor]:
        pos = self.layout.positions
        full = F.smooth_l1_loss(recon, target, reduction="none")
        root_weight = self.loss_cfg.root_weight if root_weight is None else root_weight
        if root_weight != 1.0:
            weight = torch.ones(full.shape[-1], device=full.device, dtype=full.dtype)
            weight[: self.layout.root_height.stop] = root_weight
            full = full * weight
        position = F.smooth_l1_loss(recon[..., pos], target[..., pos], reduction="none")
        if mask is None:
            return {"recon": full.mean(), "position": position.mean()}
        return {"recon": masked_mean(full, mask), "position": masked_mean(position, mask)}

    def _frozen_parameters(self) -> list[torch.nn.Parameter]:
        """What the decoder refinement does not train: every tokenizer parameter outside a decoder."""
        return [p for name, p in self.tokenizer.named_parameters() if "decoder" not in name.split(".")]

    def _refine_step(self, batch: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            indices = self.tokenizer.encode(batch)  # no EMA update, no usage counted
        recon = self.tokenizer.reconstruct(indices)
        parts = self.losses(recon, batch, root_weight=self.refine_cfg.root_weight)
        loss = parts["recon"] + self.loss_cfg.position_weight * parts["position"]
        if self.refine_cfg.path_weight > 0:
            parts["path_m"] = self.root_path_distance(recon, batch)
            loss = loss + self.refine_cfg.path_weight * parts["path_m"]
        # DDP waits for a gradient of every parameter: the frozen ones get zeros, dropped before the step.
        loss = loss + 0.0 * sum(p.sum() for p in self._frozen_parameters())
        if not logged_step(self):
            return loss
        metrics = {"train/loss": loss, "train/recon": parts["recon"], "train/position": parts["position"]}
        if "path_m" in parts:
            metrics["train/root_path_m"] = parts["path_m"]
        self.log_dict(metrics, on_step=True, on_epoch=False)
        self.log("loss", loss, prog_bar=True, logger=False)
        return loss

    def on_train_batch_start(self, batch, batch_idx: int) -> None:
        if self.refining:
            # The training windows switch to clip starts where the dataset has them (its share is
            # refine.start_windows); a loader fetches a batch or two ahead, so they begin that late.
            dataset = getattr(self.trainer.train_dataloader, "dataset", None)
            if hasattr(dataset, "at_start") and not dataset.at_start:  # a MotionWindowDataset
                dataset.at_start = True

    def on_before_optimizer_step(self, optimizer) -> None:
        if self.refining:
            # No gradient, no AdamW update: momentum and weight decay would otherwise move them.
            for p in self._frozen_parameters():
                p.grad = None

    def training_step(self, batch: torch.Tensor, batch_idx: int) -> torch.Tensor:
        if self.refining:
            return self._refine_step(batch)
        out = self.tokenizer(batch)
        parts = self.losses(out.reconstruction, batch)
        loss = (
            parts["recon"]
            + self.loss_cfg.position_weight * parts["position"]
            + self.loss_cfg.commit_weight * out.commit_loss
        )
        if self.loss_cfg.global_weight > 0:
            parts["global_m"] = (self.joints(out.reconstruction) - self.joints(batch)).norm(dim=-1).mean()
            loss = loss + self.loss_cfg.global_weight * parts["global_m"]
        if self.loss_cfg.path_weight > 0:
            parts["path_m"] = self.root_path_distance(out.reconstruction, batch)
            loss = loss + self.loss_cfg.path_weight * parts["path_m"]
        self.last_perplexities = {name: float(p) for name, p in out.perplexities.items()}
        if not logged_step(self):  # the values below only go to the loggers
            return loss
        metrics = {
            "train/loss": loss,
            "train/recon": parts["recon"],
            "train/position": parts["position"],
            "train/commit": out.commit_loss,
        }
        if "global_m" in parts:
            metrics["train/global_position_m"] = parts["global_m"]
        if "path_m" in parts:
            metrics["train/root_path_m"] = parts["path_m"]
        for name, quantizer in self.quantizers.items():
            active = quantizer.window_active()
            metrics[metric_name("codebook", name, "perplexity")] = out.perplexities[name]
            # Codes used since the last reset (the collapse monitor's window is another: collapse/*).
            metrics[metric_name("codebook", name, "used_since_reset")] = float(active)
            metrics[metric_name("codebook", name, "used_since_reset_fraction")] = active / quantizer.num_codes
        self.log_dict(metrics, prog_bar=False, on_step=True, on_epoch=False)
        self.log("loss", loss, prog_bar=True, logger=False)
        return loss

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        """Features of normalized x (..., n): all D, or only the first n of them."""
        n = x.shape[-1]
        return x * self.std[:n] + self.mean[:n]

    def joints(self, x: torch.Tensor) -> torch.Tensor:
        """Joint positions (B, T, J, 3) in metres of normalized features (B, T, D), or of only their
        first `joint_features` (B, T, 4 + 3(J-1)), the root and joint positions they are recovered from."""
        partial = x.shape[-1] != self.std.shape[-1]
        return (
            recover_from_ric(self.denormalize(x).float(), self.skeleton.num_joints, positions_only=partial)
            * self.skeleton.unit_scale
        )

    @property
    def joint_features(self) -> int:
        """How many leading features the joints are recovered from (67 of 263)."""
        return self.layout.positions.stop

    @torch.no_grad()
    def encode(self, x: torch.Tensor, encoding: CodeSearchConfig | None = None) -> torch.Tensor:
        """Code indices (B, T // 4), or (B, T // 4, 2) part-aware, of normalized features (B, T, D)
        whose clips all have T frames, as `encoding` (default: `encode_cfg`) says: the nearest codes
        (candidates 1) or those the code search picks. What tokenizes datasets for stage 2,
        reconstruction metrics and the kept frames of edits; training and the refinement quantize to
        the nearest code."""
        return search_codes(self.tokenizer, x, self.joints, encoding or self.encode_cfg, self.joint_features)

    def root_path(self, x: torch.Tensor) -> torch.Tensor:
        """Root x/z path (B, T, 2) in metres of normalized features (B, T, D), from 0 at the first frame."""
        # Only the root features (yaw and x/z velocity, height) are read: the rest is not de-normalized.
        _, root = recover_root_rot_pos(self.denormalize(x[..., : self.layout.root_height.stop]).float())
        return root[..., [0, 2]] * self.skeleton.unit_scale

    def root_path_distance(self, recon: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Mean distance (m) between the root paths of normalized features (B, T, D): the root-path
        loss of the tokenizer's steps (loss.path_weight) and of the refinement (refine.path_weight)."""
        return (self.root_path(recon) - self.root_path(target)).norm(dim=-1).mean()

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        motion, lengths = batch["motion"], batch["lengths"]
        out = self.tokenizer(motion)
        mask = torch.arange(motion.shape[1], device=motion.device)[None] < lengths[:, None]
        parts = self.losses(out.reconstruction, motion, mask)
        joints_gt, joints_rec = self.joints(motion), self.joints(out.reconstruction)
        error_global = (joints_gt - joints_rec).norm(dim=-1).mean(-1)  # (B, T)
        error = (
            ((joints_gt - joints_gt[..., :1, :]) - (joints_rec - joints_rec[..., :1, :]))
            .norm(dim=-1)
            .mean(-1)
        )
        n = mask.sum()
        self.val_recon.update(parts["recon"], weight=n)
        self.val_mpjpe.update(masked_mean(error, mask) * 1000.0, weight=n)
        self.val_mpjpe_global.update(masked_mean(error_global, mask) * 1000.0, weight=n)
        if batch_idx == 0:
            self.preview_batch = {
                "reference": joints_gt.detach().cpu(),
                "reconstruction": joints_rec.detach().cpu(),
                "lengths": lengths.detach().cpu(),
                "names": batch.get("names"),
            }

    def on_validation_epoch_end(self) -> None:
        self.log_dict(
            {
                "val/recon": self.val_recon.compute(),
                "val/mpjpe_root_aligned_mm": self.val_mpjpe.compute(),
                "val/mpjpe_global_mm": self.val_mpjpe_global.compute(),
            },
            prog_bar=True,
        )
        self.val_recon.reset()
        self.val_mpjpe.reset()
        self.val_mpjpe_global.reset()

    def configure_optimizers(self):
        steps, max_steps = self.refine_cfg.steps, self.trainer.max_steps
        if steps < 0 or (steps > 0 and max_steps <= steps):
            raise ValueError(
                f"refine.steps={steps} with a fit of max_steps={max_steps}: the decoder refinement takes the "
                "fit's last refine.steps, after the codebook has trained; set refine.steps >= 0 and a step "
                "budget (trainer.max_steps) above it"
            )
        start = self.refine_start
        tail = None if start is None else (start, steps, self.refine_cfg.lr / self.optim_cfg.lr)
        return build_optimizer(
            self.parameters(),
            self.optim_cfg,
            foreach=True,
            tail=tail,
            total_steps=self.trainer.max_steps,
        )

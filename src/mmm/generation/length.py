"""Motion length from text: a small classifier over token counts, as MoMask's length estimator.

Generation needs a target length. When the user gives none, `LengthEstimator` predicts it from the
caption's sentence embedding (the same frozen text encoder as stage 2): an MLP gives logits over
token counts 1..max_codes (49 = 196 frames / 4), trained with cross-entropy. `predict` takes the
most likely count or samples one (MoMask samples); `frames` multiplies by the tokenizer's
downsampling (4).

`LengthEstimatorModule` trains it on (sentence embedding, token count) pairs and reports, on
validation, the exact accuracy, the accuracy within ±1 and ±2 tokens and the mean absolute error
in frames of the most likely count (and the error of the distribution's median). Its hyper-parameters are plain dicts, so checkpoints load with
torch.load(weights_only=True); `load_length_estimator(path)` gives the network back in eval mode.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import lightning as L
import torch
import torch.nn as nn
import torch.nn.functional as F
from torchmetrics import MeanMetric

from mmm.tokenizer.module import OptimConfig, _as, warmup_step_schedule


@dataclass
class LengthModelConfig:
    hidden_dim: int = 256
    num_layers: int = 2  # hidden layers: sentence -> hidden (-> hidden)* -> max_codes
    dropout: float = 0.1
    max_codes: int = 49  # counts 1..max_codes are the classes (196 frames / 4)
    unit_length: int = 4  # frames per token (the tokenizer's temporal downsampling)

    def __post_init__(self):
        if self.num_layers < 1 or self.hidden_dim < 1 or self.max_codes < 1 or self.unit_length < 1:
            raise ValueError(f"length model: num_layers, hidden_dim, max_codes and unit_length must be positive, got {self}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"length model: dropout must be in [0, 1), got {self.dropout}")


PREDICT_MODES = ("mode", "sample", "median")


def median_count(logits: torch.Tensor) -> torch.Tensor:
    """(B, max_codes) logits -> (B,) the smallest count whose cumulative probability reaches 1/2."""
    cumulative = torch.softmax(logits.float(), dim=-1).cumsum(-1)
    return (cumulative < 0.5).sum(-1).clamp(max=logits.shape[-1] - 1) + 1


class LengthEstimator(nn.Module):
    """Sentence embedding (B, Ds) -> logits (B, max_codes); class c is a count of c + 1 tokens."""

    def __init__(self, sentence_dim: int, cfg: LengthModelConfig | dict | None = None):
        super().__init__()
        cfg = _as(LengthModelConfig, cfg) if cfg is not None else LengthModelConfig()
        self.cfg, self.sentence_dim = cfg, int(sentence_dim)
        layers: list[nn.Module] = []
        width = self.sentence_dim
        for _ in range(cfg.num_layers):
            layers += [nn.Linear(width, cfg.hidden_dim), nn.LayerNorm(cfg.hidden_dim), nn.GELU(), nn.Dropout(cfg.dropout)]
            width = cfg.hidden_dim
        self.mlp = nn.Sequential(*layers)
        self.head = nn.Linear(width, cfg.max_codes)

    @property
    def max_codes(self) -> int:
        return self.cfg.max_codes

    @property
    def unit_length(self) -> int:
        return self.cfg.unit_length

    def forward(self, sentence: torch.Tensor) -> torch.Tensor:
        return self.logits(sentence)

    def logits(self, sentence: torch.Tensor) -> torch.Tensor:
        if sentence.dim() != 2 or sentence.shape[1] != self.sentence_dim:
            raise ValueError(f"expected sentence embeddings (B, {self.sentence_dim}), got {tuple(sentence.shape)}")
        return self.head(self.mlp(sentence.to(self.head.weight.dtype)))

    @torch.no_grad()
    def predict(
        self,
        sentence: torch.Tensor,
        mode: str = "mode",
        generator: torch.Generator | None = None,
        temperature: float = 1.0,
        min_codes: int = 1,
        max_codes: int | None = None,
    ) -> torch.Tensor:
        """(B,) int64 token counts in [min_codes, max_codes] (default 1..self.max_codes).

        mode="mode": the most likely count; mode="sample": a draw from softmax(logits / temperature)
        (what MoMask does), reproducible with `generator`; mode="median": the median of the
        distribution (the count with the least expected absolute error).
        """
        if mode not in PREDICT_MODES:
            raise ValueError(f"predict: mode must be one of {', '.join(PREDICT_MODES)}, got {mode!r}")
        high = self.max_codes if max_codes is None else int(max_codes)
        if not 1 <= min_codes <= high <= self.max_codes:
            raise ValueError(f"predict: need 1 <= min_codes ({min_codes}) <= max_codes ({high}) <= {self.max_codes}")
        logits = self.logits(sentence).float()
        counts = torch.arange(1, self.max_codes + 1, device=logits.device)
        allowed = (counts >= min_codes) & (counts <= high)
        logits = logits.masked_fill(~allowed, float("-inf"))  # at least one class stays finite
        if mode == "mode":
            return logits.argmax(-1) + 1
        if mode == "median":
            return median_count(logits)
        if temperature <= 0:
            raise ValueError(f"predict: temperature must be positive, got {temperature}")
        probs = torch.softmax(logits / temperature, dim=-1)
        return torch.multinomial(probs, 1, generator=generator).squeeze(1) + 1

    def frames(self, sentence: torch.Tensor, *args, **kwargs) -> torch.Tensor:
        """(B,) motion lengths in frames: predicted token counts × unit_length (arguments as predict)."""
        return self.predict(sentence, *args, **kwargs) * self.unit_length


def length_metrics(predicted: torch.Tensor, target: torch.Tensor, unit_length: int = 4) -> dict[str, torch.Tensor]:
    """Per-sample exact / within ±1 / within ±2 token hits (float) and absolute error in frames."""
    error = (predicted.long() - target.long()).abs()
    return {
        "acc": (error == 0).float(),
        "acc_within1": (error <= 1).float(),
        "acc_within2": (error <= 2).float(),
        "mae_frames": error.float() * unit_length,
    }


class LengthEstimatorModule(L.LightningModule):
    """Trains a LengthEstimator on batches {"sentence" (B, Ds) float, "codes" (B,) int token counts}.

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
    ):
        super().__init__()
        model = _as(LengthModelConfig, model) if model is not None else LengthModelConfig()
        optim = _as(OptimConfig, optim) if optim is not None else OptimConfig(lr=1e-3, warmup_steps=0)
        self.save_hyperparameters(
            {
                "sentence_dim": int(sentence_dim), "model": asdict(model), "optim": asdict(optim), "label_smoothing": float(label_smoothing),
                "text_encoder": dict(text_encoder or {}), "stage1": dict(stage1 or {}),
            }, logger=False
        )
        self.model_cfg, self.optim_cfg, self.label_smoothing = model, optim, float(label_smoothing)
        self.estimator = LengthEstimator(sentence_dim, model)
        self.val_metrics = nn.ModuleDict({name: MeanMetric() for name in ("loss", "acc", "acc_within1", "acc_within2", "mae_frames", "mae_frames_median")})

    def _loss(self, logits: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        target = codes.long().clamp(1, self.model_cfg.max_codes) - 1
        return F.cross_entropy(logits.float(), target, label_smoothing=self.label_smoothing)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        logits = self.estimator.logits(batch["sentence"])
        loss = self._loss(logits, batch["codes"])
        hits = length_metrics(logits.argmax(-1) + 1, batch["codes"], self.model_cfg.unit_length)
        self.log_dict({"train/loss": loss, "train/acc_within1": hits["acc_within1"].mean()}, on_step=True, on_epoch=False)
        self.log("loss", loss, prog_bar=True, logger=False)
        return loss

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        logits = self.estimator.logits(batch["sentence"])
        n = len(batch["codes"])
        self.val_metrics["loss"].update(F.cross_entropy(logits.float(), batch["codes"].long().clamp(1, self.model_cfg.max_codes) - 1), weight=n)
        for name, values in length_metrics(logits.argmax(-1) + 1, batch["codes"], self.model_cfg.unit_length).items():
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
        cfg = self.optim_cfg
        optimizer = torch.optim.AdamW(self.estimator.parameters(), lr=cfg.lr, betas=tuple(cfg.betas), weight_decay=cfg.weight_decay)
        schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, warmup_step_schedule(cfg.warmup_steps, list(cfg.milestones), cfg.gamma))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step", "name": "train/lr"}}


def load_length_estimator(path: str | Path, map_location: str | torch.device = "cpu") -> LengthEstimator:
    """The LengthEstimator of a LengthEstimatorModule checkpoint, in eval mode (weights_only load).

    The returned network carries `.text_encoder` and `.stage1` (the identities it was trained
    with) so a caller can check it is used with the same text encoder.
    """
    from mmm.checkpoints import CheckpointError, load_checkpoint, load_state

    ckpt = load_checkpoint(path, "length", map_location=map_location)
    hp = ckpt["hyper_parameters"]
    try:
        estimator = LengthEstimator(hp["sentence_dim"], hp["model"])
    except (TypeError, ValueError, KeyError) as e:
        raise CheckpointError(f"{path}: its hyper-parameters do not describe a length estimator ({e}); use the checkpoint as training wrote it") from None
    prefix = "estimator."
    load_state(estimator, {k[len(prefix):]: v for k, v in ckpt["state_dict"].items() if k.startswith(prefix)}, path, "length")
    estimator.text_encoder = dict(hp.get("text_encoder") or {})
    estimator.stage1 = dict(hp.get("stage1") or {})
    return estimator.eval()

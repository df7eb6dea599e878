"""Motion length from text: a small classifier over token counts, as MoMask's length estimator.

Generation needs a target length. When the user gives none, `LengthEstimator` predicts it from the
caption (the same frozen text encoder as stage 2): an MLP gives logits over token counts
1..max_codes (49 = 196 frames / 4), trained with cross-entropy. `predict` takes the most likely
count or samples one (MoMask samples); `frames` multiplies by the tokenizer's downsampling (4).

What the MLP reads (`pooling`): MoMask's "sentence" is the sentence embedding alone; "words" adds
an attention-weighted mean of the caption's per-token features. A sentence embedding of "a man
walks forward and jumps" lies near "a man jumps", so the first estimator gives it a single
action's length; the word pool sees the second verb (README, "Generating and editing").

This file is the network and its inference side (no Lightning): `LengthEstimator`, its config,
`length_metrics` and `load_length_estimator(path)`, which gives the network of a training
checkpoint back in eval mode. `LengthEstimatorModule` (mmm.generation.length_module) trains it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn

from mmm.checkpoints import CheckpointError, load_checkpoint, load_state
from mmm.config import as_config

POOLINGS = ("sentence", "words")


@dataclass
class LengthModelConfig:
    hidden_dim: int = 256
    num_layers: int = 2  # hidden layers: sentence -> hidden (-> hidden)* -> max_codes
    dropout: float = 0.1
    max_codes: int = 49  # counts 1..max_codes are the classes (196 frames / 4)
    unit_length: int = 4  # frames per token (the tokenizer's temporal downsampling)
    # "sentence": the sentence embedding only (MoMask's; checkpoints without the key); "words": an
    # attention pool over the per-token features beside it.
    pooling: str = "sentence"

    def __post_init__(self):
        if self.pooling not in POOLINGS:
            raise ValueError(
                f"length model: pooling must be one of {', '.join(POOLINGS)}, got {self.pooling!r}"
            )
        if self.num_layers < 1 or self.hidden_dim < 1 or self.max_codes < 1 or self.unit_length < 1:
            raise ValueError(
                "length model: num_layers, hidden_dim, max_codes and unit_length must be positive, got "
                f"{self}"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"length model: dropout must be in [0, 1), got {self.dropout}")


PREDICT_MODES = ("mode", "sample", "median")


def median_count(logits: torch.Tensor) -> torch.Tensor:
    """(B, max_codes) logits -> (B,) the smallest count whose cumulative probability reaches 1/2."""
    cumulative = torch.softmax(logits.float(), dim=-1).cumsum(-1)
    return (cumulative < 0.5).sum(-1).clamp(max=logits.shape[-1] - 1) + 1


class LengthEstimator(nn.Module):
    """Caption -> logits (B, max_codes); class c is a count of c + 1 tokens.

    Reads the sentence embedding (B, Ds), and with pooling "words" also the per-token features
    (B, L, Dw) with their mask (B, L) (True at real tokens): each token is projected to hidden_dim,
    scored, and the softmax-weighted mean joins the sentence embedding at the MLP's input.
    """

    def __init__(
        self, sentence_dim: int, cfg: LengthModelConfig | dict | None = None, word_dim: int | None = None
    ):
        super().__init__()
        cfg = as_config(LengthModelConfig, cfg) if cfg is not None else LengthModelConfig()
        self.cfg, self.sentence_dim = cfg, int(sentence_dim)
        width = self.sentence_dim
        if cfg.pooling == "words":
            if not word_dim:
                raise ValueError("length model: pooling 'words' needs the text encoder's word_dim")
            self.word_dim = int(word_dim)
            self.word_proj = nn.Linear(self.word_dim, cfg.hidden_dim)
            self.word_score = nn.Linear(cfg.hidden_dim, 1)
            width += cfg.hidden_dim
        layers: list[nn.Module] = []
        for _ in range(cfg.num_layers):
            layers += [
                nn.Linear(width, cfg.hidden_dim),
                nn.LayerNorm(cfg.hidden_dim),
                nn.GELU(),
                nn.Dropout(cfg.dropout),
            ]
            width = cfg.hidden_dim
        self.mlp = nn.Sequential(*layers)
        self.head = nn.Linear(width, cfg.max_codes)

    @property
    def max_codes(self) -> int:
        return self.cfg.max_codes

    @property
    def unit_length(self) -> int:
        return self.cfg.unit_length

    @property
    def reads_words(self) -> bool:
        return self.cfg.pooling == "words"

    def forward(self, sentence, words=None, word_mask=None) -> torch.Tensor:
        return self.logits(sentence, words, word_mask)

    def logits(
        self, sentence: torch.Tensor, words: torch.Tensor | None = None, word_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        if sentence.dim() != 2 or sentence.shape[1] != self.sentence_dim:
            raise ValueError(
                f"expected sentence embeddings (B, {self.sentence_dim}), got {tuple(sentence.shape)}"
            )
        x = sentence.to(self.head.weight.dtype)
        if self.reads_words:
            if words is None or word_mask is None:
                raise ValueError("this length estimator reads the caption's words: pass words and word_mask")
            if words.dim() != 3 or words.shape[0] != len(sentence) or words.shape[2] != self.word_dim:
                raise ValueError(
                    f"expected word features (B={len(sentence)}, L, {self.word_dim}), "
                    f"got {tuple(words.shape)}"
                )
            tokens = torch.tanh(self.word_proj(words.to(x.dtype)))
            weight = self.word_score(tokens).squeeze(-1).masked_fill(~word_mask.bool(), float("-inf"))
            pooled = (weight.softmax(-1).unsqueeze(-1) * tokens).sum(1)
            x = torch.cat([x, pooled], dim=-1)
        return self.head(self.mlp(x))

    @torch.no_grad()
    def predict(
        self,
        sentence: torch.Tensor,
        mode: str = "mode",
        generator: torch.Generator | None = None,
        temperature: float = 1.0,
        min_codes: int = 1,
        max_codes: int | None = None,
        words: torch.Tensor | None = None,
        word_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(B,) int64 token counts in [min_codes, max_codes] (default 1..self.max_codes); words and
        word_mask for an estimator that reads them.

        mode="mode": the most likely count; mode="sample": a draw from softmax(logits / temperature)
        (what MoMask does), reproducible with `generator`; mode="median": the median of the
        distribution (the count with the least expected absolute error).
        """
        if mode not in PREDICT_MODES:
            raise ValueError(f"predict: mode must be one of {', '.join(PREDICT_MODES)}, got {mode!r}")
        high = self.max_codes if max_codes is None else int(max_codes)
        if not 1 <= min_codes <= high <= self.max_codes:
            raise ValueError(
                f"predict: need 1 <= min_codes ({min_codes}) <= max_codes ({high}) <= {self.max_codes}"
            )
        logits = self.logits(sentence, words, word_mask).float()
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


def length_metrics(
    predicted: torch.Tensor, target: torch.Tensor, unit_length: int = 4
) -> dict[str, torch.Tensor]:
    """Per-sample exact / within ±1 / within ±2 token hits (float) and absolute error in frames."""
    error = (predicted.long() - target.long()).abs()
    return {
        "acc": (error == 0).float(),
        "acc_within1": (error <= 1).float(),
        "acc_within2": (error <= 2).float(),
        "mae_frames": error.float() * unit_length,
    }


def load_length_estimator(path: str | Path, map_location: str | torch.device = "cpu") -> LengthEstimator:
    """The LengthEstimator of a LengthEstimatorModule checkpoint, in eval mode (weights_only load).

    The returned network carries `.text_encoder` and `.stage1` (the identities it was trained
    with) so a caller can check it is used with the same text encoder.
    """
    ckpt = load_checkpoint(path, "length", map_location=map_location)
    hp = ckpt["hyper_parameters"]
    try:
        estimator = LengthEstimator(hp["sentence_dim"], hp["model"], hp.get("word_dim"))
    except (TypeError, ValueError, KeyError) as e:
        raise CheckpointError(
            f"{path}: its hyper-parameters do not describe a length estimator ({e}); use the checkpoint as "
            "training wrote it"
        ) from None
    prefix = "estimator."
    load_state(
        estimator,
        {k[len(prefix) :]: v for k, v in ckpt["state_dict"].items() if k.startswith(prefix)},
        path,
        "length",
    )
    estimator.text_encoder = dict(hp.get("text_encoder") or {})
    estimator.stage1 = dict(hp.get("stage1") or {})
    return estimator.eval()

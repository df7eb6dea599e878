"""The package's own text-motion evaluator: a motion encoder and a text head trained contrastively.

Any dataset in the HumanML3D layout (the synthetic default included) can train one, so the
metrics (R-precision, MM-Dist, FID, diversity) exist where the published T2M evaluator does not.

    motion (B, T, D) normalized, lengths (B,)
      -> two strided convs (kernel 4, stride 2, LeakyReLU 0.2): (B, T // 4, H), zeroed past each length
      -> bidirectional GRU over length // 4 steps; both final states (B, 2H)
      -> LayerNorm, Linear -> (B, E)
    sentence embedding (B, Ds) of a frozen pretrained text encoder (cached; MiniLM by default)
      -> MLP (Linear, LayerNorm, GELU, dropout, Linear) -> (B, E)

Trained with a symmetric InfoNCE loss over the batch with a learnable temperature (CLIP's
log-scale, capped at 100). Captions of the same meaning are common in text-motion data (the
synthetic set repeats templates across clips), so pairs whose frozen sentence embeddings are
nearly identical (cosine >= `false_negative_threshold`) can be left out of each other's negatives.

`ContrastiveEvaluator` holds the dataset's Mean/Std in buffers: a checkpoint is self-contained.
Embeddings are L2-normalized by default (`normalize`), so Euclidean distances (R-precision,
MM-Dist) rank like the cosine similarities it was trained on.

This file is the network and its inference side (no Lightning): the networks and their config,
retrieval scoring, `load_contrastive_evaluator(path)`, which gives (evaluator in eval mode, info),
and `EvaluatorEmbedder`, which takes raw features and caption strings. The loss and
`ContrastiveEvaluatorModule`, which trains it, are in mmm.evaluation.contrastive_module.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from mmm.checkpoints import CheckpointError, load_checkpoint, load_state, text_encoder_options
from mmm.config import as_config
from mmm.evaluation.metrics import matching_score, r_precision_hits
from mmm.text import build_text_encoder
from mmm.training.configs import ContrastiveModelConfig

DOWNSAMPLE = 4  # the motion encoder's temporal downsampling (two stride-2 convs)
MIN_FRAMES = 4  # the shortest motion it accepts


def valid_mask(lengths: torch.Tensor, T: int) -> torch.Tensor:
    """(B,) lengths -> (B, T) bool, True at the first lengths[b] positions."""
    return torch.arange(T, device=lengths.device) < lengths.to(torch.long).unsqueeze(1)


def reverse_within(x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """(B, T, C): each row's first lengths[b] steps in reverse order, the padding left in place."""
    t = torch.arange(x.shape[1], device=x.device).unsqueeze(0)
    lengths = lengths.to(x.device).unsqueeze(1)
    index = torch.where(t < lengths, lengths - 1 - t, t)
    return x.gather(1, index.unsqueeze(-1).expand(-1, -1, x.shape[-1]))


class MotionEncoder(nn.Module):
    """Normalized features (B, T, D) with lengths (B,) -> (B, E); frames past a length never count."""

    def __init__(self, feature_dim: int, hidden_dim: int, embed_dim: int, dropout: float):
        super().__init__()
        self.conv1 = nn.Conv1d(feature_dim, hidden_dim, kernel_size=4, stride=2, padding=1)
        self.conv2 = nn.Conv1d(hidden_dim, hidden_dim, kernel_size=4, stride=2, padding=1)
        self.act = nn.LeakyReLU(0.2)
        self.dropout = nn.Dropout(dropout)
        # A bidirectional GRU as two GRUs, the second over each motion reversed within its length:
        # the same result as a packed bidirectional GRU, at the speed of the fused padded kernels
        # (packed sequences backpropagate step by step, several times slower on a CPU).
        self.gru_forward = nn.GRU(hidden_dim, hidden_dim, batch_first=True)
        self.gru_backward = nn.GRU(hidden_dim, hidden_dim, batch_first=True)
        self.out = nn.Sequential(nn.LayerNorm(2 * hidden_dim), nn.Linear(2 * hidden_dim, embed_dim))

    def forward(self, motion: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        lengths = lengths.to(device=motion.device, dtype=torch.long)
        # Zero everything past each length, after the input and after each conv: a padded motion
        # then sees exactly the zeros an unpadded one sees from the convs' own padding.
        x = (motion * valid_mask(lengths, motion.shape[1]).unsqueeze(-1).to(motion.dtype)).transpose(1, 2)
        for conv in (self.conv1, self.conv2):
            x = self.act(conv(x))
            lengths = lengths // 2  # a k4 s2 p1 conv maps L frames to floor(L / 2)
            x = x * valid_mask(lengths, x.shape[-1]).unsqueeze(1).to(x.dtype)
        x = self.dropout(x.transpose(1, 2))
        # The state after each motion's last real step: the GRUs are causal, so later (padded)
        # steps cannot change it.
        last = (lengths - 1).view(-1, 1, 1).expand(-1, 1, x.shape[-1])
        forward = self.gru_forward(x)[0].gather(1, last).squeeze(1)
        backward = self.gru_backward(reverse_within(x, lengths))[0].gather(1, last).squeeze(1)
        return self.out(torch.cat((forward, backward), dim=-1))


class TextHead(nn.Module):
    """Frozen sentence embeddings (B, Ds) -> (B, E)."""

    def __init__(self, sentence_dim: int, hidden_dim: int, embed_dim: int, dropout: float):
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(sentence_dim, hidden_dim),
            nn.LayerNorm(hidden_dim),
            nn.GELU(),
            nn.Dropout(dropout),
            nn.Linear(hidden_dim, embed_dim),
        )

    def forward(self, sentence: torch.Tensor) -> torch.Tensor:
        return self.mlp(sentence)


class ContrastiveEvaluator(nn.Module):
    """Motion and text embeddings in one space; holds the training data's Mean/Std (buffers)."""

    def __init__(
        self,
        feature_dim: int,
        sentence_dim: int,
        cfg: ContrastiveModelConfig | dict | None = None,
        mean: np.ndarray | torch.Tensor | None = None,
        std: np.ndarray | torch.Tensor | None = None,
    ):
        super().__init__()
        cfg = as_config(ContrastiveModelConfig, cfg) if cfg is not None else ContrastiveModelConfig()
        self.cfg, self.feature_dim, self.sentence_dim = cfg, int(feature_dim), int(sentence_dim)
        self.motion_encoder = MotionEncoder(self.feature_dim, cfg.hidden_dim, cfg.embed_dim, cfg.dropout)
        self.text_head = TextHead(self.sentence_dim, cfg.text_hidden_dim, cfg.embed_dim, cfg.dropout)
        self.logit_scale = nn.Parameter(torch.tensor(math.log(1.0 / cfg.init_temperature)))
        mean = torch.zeros(self.feature_dim) if mean is None else torch.as_tensor(mean, dtype=torch.float32)
        std = torch.ones(self.feature_dim) if std is None else torch.as_tensor(std, dtype=torch.float32)
        if mean.shape != (self.feature_dim,) or std.shape != (self.feature_dim,):
            raise ValueError(
                f"mean/std must be ({self.feature_dim},), got {tuple(mean.shape)} / {tuple(std.shape)}"
            )
        self.register_buffer("mean", mean.clone())
        self.register_buffer("std", std.clone())

    @property
    def embed_dim(self) -> int:
        return self.cfg.embed_dim

    def scale(self) -> torch.Tensor:
        """The InfoNCE logit scale, 1 / temperature, capped at max_logit_scale."""
        return self.logit_scale.exp().clamp(max=self.cfg.max_logit_scale)

    def normalize_features(self, features: torch.Tensor) -> torch.Tensor:
        """Raw features (..., D) -> normalized with the stored dataset statistics."""
        return (features.to(self.mean.dtype) - self.mean) / self.std

    def _finish(self, z: torch.Tensor) -> torch.Tensor:
        return F.normalize(z, dim=-1) if self.cfg.normalize else z

    def motion_features(self, features_normalized: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """(B, T, D), (B,) -> (B, E) before any L2 normalization."""
        if features_normalized.dim() != 3 or features_normalized.shape[-1] != self.feature_dim:
            raise ValueError(
                f"expected motion features (B, T, {self.feature_dim}), got {tuple(features_normalized.shape)}"
            )
        lengths = torch.as_tensor(lengths, dtype=torch.long)
        if lengths.shape != (features_normalized.shape[0],):
            raise ValueError(
                f"expected lengths ({features_normalized.shape[0]},), got {tuple(lengths.shape)}"
            )
        if len(lengths) and (
            int(lengths.min()) < MIN_FRAMES or int(lengths.max()) > features_normalized.shape[1]
        ):
            raise ValueError(
                f"motion lengths must lie in [{MIN_FRAMES}, T={features_normalized.shape[1]}], got "
                f"{int(lengths.min())}..{int(lengths.max())}"
            )
        return self.motion_encoder(features_normalized.to(self.mean.dtype), lengths)

    def text_features(self, sentence_embeddings: torch.Tensor) -> torch.Tensor:
        if sentence_embeddings.dim() != 2 or sentence_embeddings.shape[-1] != self.sentence_dim:
            raise ValueError(
                f"expected sentence embeddings (B, {self.sentence_dim}), got "
                f"{tuple(sentence_embeddings.shape)}"
            )
        return self.text_head(sentence_embeddings.to(self.mean.dtype))

    def embed_motions(self, features_normalized: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """Normalized features (B, T, D) with lengths (B,) -> (B, E)."""
        return self._finish(self.motion_features(features_normalized, lengths))

    def embed_sentences(self, sentence_embeddings: torch.Tensor) -> torch.Tensor:
        """The frozen text encoder's sentence embeddings (B, Ds) -> (B, E)."""
        return self._finish(self.text_features(sentence_embeddings))

    def forward(
        self, motion: torch.Tensor, lengths: torch.Tensor, sentence: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(motion embeddings (B, E), text embeddings (B, E)), as embed_* return them."""
        return self.embed_motions(motion, lengths), self.embed_sentences(sentence)


# ---------------------------------------------------------------------------------------- retrieval


def matching_ranks(text: torch.Tensor, motion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For B pairs: (rank of motion i among all motions by Euclidean distance to text i,
    rank of text i among all texts by distance to motion i), 0 = nearest; ties count in favour."""
    dist = torch.cdist(text.float(), motion.float())
    own = dist.diagonal()
    return (dist < own.unsqueeze(1)).sum(1), (dist < own.unsqueeze(0)).sum(0)


def retrieval_metrics(
    texts: Sequence[torch.Tensor], motions: Sequence[torch.Tensor], top_k: int = 3
) -> dict[str, float]:
    """R-precision over batches of pairs (usually 32 each), as the evaluation protocol computes it
    (mmm.evaluation.metrics): per k <= top_k the fraction of texts whose own motion is among the k
    of its batch nearest to it (Euclidean), and the mean distance text i - motion i (MM-Dist)."""
    if not len(texts):
        raise ValueError("retrieval_metrics: no batch of pairs")
    hits = sum(r_precision_hits(t, m, top_k) for t, m in zip(texts, motions))
    n = sum(len(t) for t in texts)
    out = {f"r_precision_top{k}": float(hits[k - 1]) / n for k in range(1, top_k + 1)}
    out["matching_distance"] = matching_score(torch.cat(list(texts)), torch.cat(list(motions)))
    return out


def load_contrastive_evaluator(
    path: str | Path, map_location: str | torch.device = "cpu"
) -> tuple[ContrastiveEvaluator, dict]:
    """(ContrastiveEvaluator in eval mode, info) from a ContrastiveEvaluatorModule checkpoint,
    loaded with weights_only=True.

    info: {"text_encoder": {"name", "identity", ...}, "data": {...}, "data_fingerprint",
    "mean" (D,), "std" (D,), "feature_dim", "sentence_dim", "model": {...}, "global_step", "path"}.
    Anything but an intact evaluator checkpoint is a CheckpointError naming the file.
    """
    ckpt = load_checkpoint(path, "evaluator", map_location=map_location)
    hp = ckpt["hyper_parameters"]
    state = ckpt["state_dict"]
    prefix = "evaluator."
    try:
        evaluator = ContrastiveEvaluator(hp["feature_dim"], hp["sentence_dim"], hp["model"])
    except (TypeError, ValueError, KeyError) as e:
        raise CheckpointError(
            f"{path}: its hyper-parameters do not describe a contrastive evaluator ({e}); use the checkpoint "
            "as training wrote it"
        ) from None
    load_state(
        evaluator, {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}, path, "evaluator"
    )
    evaluator.eval()
    data = dict(hp.get("data") or {})
    info = {
        "text_encoder": dict(hp.get("text_encoder") or {}),
        "data": data,
        "data_fingerprint": data.get("fingerprint"),
        "mean": evaluator.mean.detach().clone(),
        "std": evaluator.std.detach().clone(),
        "feature_dim": int(hp["feature_dim"]),
        "sentence_dim": int(hp["sentence_dim"]),
        "model": dict(hp["model"]),
        "global_step": ckpt.get("global_step"),
        "path": str(path),
    }
    return evaluator, info


# ---------------------------------------------------------------------------------------- raw inputs


class EvaluatorEmbedder:
    """Embeds raw (un-normalized) features and caption strings with a ContrastiveEvaluator.

    Captions come from `caption_cache` when it holds them all, else from `text_encoder` (built
    from the identity recorded in `info` on first need when none is given). Both must be the
    encoder the evaluator was trained with: a different identity is refused.
    """

    def __init__(
        self,
        evaluator: ContrastiveEvaluator,
        info: dict | None = None,
        text_encoder=None,
        caption_cache=None,
        device: str | torch.device | None = None,
    ):
        self.info = dict(info or {})
        self.device = torch.device(device) if device is not None else evaluator.mean.device
        self.evaluator = evaluator.to(self.device).eval()
        self.expected_identity = (self.info.get("text_encoder") or {}).get("identity")
        self._encoder = None
        if text_encoder is not None:
            self._check_identity(text_encoder.identity, "text encoder")
            self._encoder = text_encoder
        if caption_cache is not None:
            self._check_identity(caption_cache.encoder_identity, "caption cache")
        self.caption_cache = caption_cache

    @classmethod
    def from_checkpoint(
        cls, path: str | Path, text_encoder=None, caption_cache=None, device: str | torch.device = "cpu"
    ) -> "EvaluatorEmbedder":
        evaluator, info = load_contrastive_evaluator(path)
        return cls(evaluator, info, text_encoder=text_encoder, caption_cache=caption_cache, device=device)

    def _check_identity(self, identity: str, what: str) -> None:
        if self.expected_identity and identity != self.expected_identity:
            raise ValueError(
                f"this evaluator was trained on sentence embeddings of {self.expected_identity!r}, but the "
                f"{what} is {identity!r}; "
                "use the text encoder it was trained with"
            )

    @property
    def text_encoder(self):
        """The text encoder: the one given, else built from the recorded name and options."""
        if self._encoder is None:
            recorded = dict(self.info.get("text_encoder") or {})
            if not recorded.get("name"):
                raise ValueError(
                    "the evaluator records no text encoder name; pass text_encoder= to EvaluatorEmbedder"
                )
            # Recorded file options (CLIP weights) are followed only inside outputs/: else pass text_encoder=.
            name, options = text_encoder_options(
                recorded, None, self.info.get("path", "the evaluator checkpoint")
            )
            encoder = build_text_encoder(name, **options)
            self._check_identity(encoder.identity, "text encoder")
            self._encoder = encoder
        return self._encoder

    def sentence_embeddings(self, captions: Sequence) -> torch.Tensor:
        """B captions (strings, or Caption objects: their .text) -> (B, Ds) frozen sentence embeddings."""
        if isinstance(captions, str):
            raise TypeError("embed_texts() takes a list of captions, not a single string")
        captions = [getattr(c, "text", c) for c in captions]
        if self.caption_cache is not None and all(c in self.caption_cache for c in captions):
            return self.caption_cache.lookup(captions).sentence
        return self.text_encoder.encode(captions).sentence

    @torch.no_grad()
    def embed_texts(self, captions: Sequence) -> torch.Tensor:
        """B captions (strings or Caption objects, as the evaluation protocol passes) -> (B, E)."""
        sentence = self.sentence_embeddings(captions).to(self.device)
        return self.evaluator.embed_sentences(sentence)

    @torch.no_grad()
    def embed_motions(
        self, features: torch.Tensor | np.ndarray, lengths: torch.Tensor | Sequence[int]
    ) -> torch.Tensor:
        """Raw features (B, T, D) (padding past each length is ignored) with lengths (B,) -> (B, E)."""
        features = torch.as_tensor(features, dtype=torch.float32).to(self.device)
        lengths = torch.as_tensor(lengths, dtype=torch.long)
        return self.evaluator.embed_motions(self.evaluator.normalize_features(features), lengths)

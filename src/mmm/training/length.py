"""Train the length estimator (`train_length(cfg)`; conf/train_length.yaml).

It reads what stage 2 reads: the dataset's items tokenized by a stage-1 model (`stage1=`: a
checkpoint, an MLflow run id, a models:/ URI; the newest finished stage-1 run when none is named)
and the cached caption embeddings of the configured text encoder, both through
`prepare_stage2_data`. Every caption of an item gives one pair (the caption's embeddings, the
item's token count). The run is tracked like the stages: resolved config, per-step loss, validation
metrics, best/last checkpoints as artifacts, tags naming the text encoder, the data and the
stage-1 model; it also logs, as `baseline/*`, what always predicting the training set's most
frequent count (and, for the error in frames, its median count) scores on validation.
"""

from __future__ import annotations

import logging
import time
from collections import Counter

import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import Dataset

from mmm.config import to_object
from mmm.data.datasets import TokenTextDataset
from mmm.data.resumable import ResumableDataLoader
from mmm.data.tokens import TokenCache
from mmm.generation.length import length_metrics
from mmm.generation.length_module import LengthEstimatorModule
from mmm.kinds import LENGTH
from mmm.training.common import (
    TrackedRun,
    TrainResult,
    log_final_metrics,
    run_target,
    text_record,
    tracked_fit,
)
from mmm.training.configs import LengthConfig, Stage2Config
from mmm.training.stage2 import prepare_stage2_data, stage1_record, stage1_tags

log = logging.getLogger(__name__)


def stage2_view(cfg_node: DictConfig) -> DictConfig:
    """The stage-2 config that names the same data, stage-1 model, text encoder and store, with
    sequences of max_codes tokens plus END: what `prepare_stage2_data` reads. It reads the nearest
    codes: a clip's token count is the same under any encoding, and they take seconds to compute
    where the code search takes minutes."""
    cfg: LengthConfig = to_object(cfg_node)
    node = OmegaConf.structured(Stage2Config)
    shared = {key: OmegaConf.to_container(cfg_node[key], resolve=True) for key in ("data", "text", "logger")}
    return OmegaConf.merge(
        node,
        {
            "seed": cfg.seed,
            "stage1": cfg.stage1,
            "stage1_output_dir": cfg.stage1_output_dir,
            "token_cache_dir": cfg.token_cache_dir,
            "token_encoding": "nearest",
            **shared,
            "model": {"transformer": {"max_tokens": cfg.model.max_codes + 1}},
        },
    )


class LengthPairs(Dataset):
    """(caption, token count) pairs: {"caption", "codes" ()}; `LengthBatch` embeds a batch of them."""

    def __init__(self, captions: list[str], codes: torch.Tensor):
        self.captions, self.codes = list(captions), codes.long()

    def __len__(self) -> int:
        return len(self.codes)

    def __getitem__(self, index: int) -> dict:
        index = index % len(self.codes)  # ShardedRandomSampler tags indices with the epoch
        return {"caption": self.captions[index], "codes": self.codes[index]}


class LengthBatch:
    """Collates LengthPairs items into {"sentence" (B, Ds), "codes" (B,)} from the caption cache,
    with "words" (B, L, Dw) and "word_mask" (B, L) when `words` is set. Picklable (loader workers)."""

    def __init__(self, caption_cache, words: bool):
        self.caption_cache, self.words = caption_cache, bool(words)

    def __call__(self, batch: list[dict]) -> dict:
        text = self.caption_cache.lookup([b["caption"] for b in batch])
        out = {"sentence": text.sentence, "codes": torch.stack([b["codes"] for b in batch])}
        if self.words:
            out["words"], out["word_mask"] = text.words, text.word_mask
        return out


def build_length_pairs(datamodule, split: str, max_codes: int) -> LengthPairs:
    """Every caption of every item of `split` with the item's token count (items without a code are
    left out); their embeddings come from the datamodule's caption cache, a batch at a time."""
    items, _ = datamodule._items(split)
    codes_of = TokenTextDataset(
        items, datamodule.tokens, unit_length=datamodule.cfg.unit_length, max_codes=max_codes, augment=False
    )
    captions, counts = [], []
    for item in items:
        n = len(codes_of.codes(item))
        if n == 0:
            continue
        for caption in item.captions:
            captions.append(caption.text)
            counts.append(n)
    if not captions:
        raise ValueError(
            f"{datamodule.root}: no {split} item has a token; the length estimator has nothing to learn from"
        )
    return LengthPairs(captions, torch.tensor(counts, dtype=torch.long))


def constant_baseline(train: LengthPairs, val: LengthPairs, unit_length: int) -> dict[str, float]:
    """Validation scores of always predicting the most frequent training count (and its value), and
    the error of always predicting the median training count (the best constant for that error)."""
    mode = Counter(train.codes.tolist()).most_common(1)[0][0]
    median = int(train.codes.median())
    hits = length_metrics(torch.full_like(val.codes, mode), val.codes, unit_length)
    median_error = length_metrics(torch.full_like(val.codes, median), val.codes, unit_length)["mae_frames"]
    return {
        "baseline/mode_codes": float(mode),
        **{f"baseline/{k}": float(v.mean()) for k, v in hits.items()},
        "baseline/median_codes": float(median),
        "baseline/median_mae_frames": float(median_error.mean()),
    }


def train_length(cfg_node: DictConfig) -> TrainResult:
    cfg: LengthConfig = to_object(cfg_node)
    started = time.perf_counter()
    L.seed_everything(cfg.seed, workers=True)
    datamodule = prepare_stage2_data(stage2_view(cfg_node))
    if (
        datamodule.tokens is None
    ):  # prepare_data opens the token cache; setup() would also build stage-2 datasets
        datamodule.tokens = TokenCache(datamodule._token_folder())
    source, text_encoder = datamodule.source, datamodule.text_encoder
    train, val = (build_length_pairs(datamodule, split, cfg.model.max_codes) for split in ("train", "val"))
    baseline = constant_baseline(train, val, cfg.model.unit_length)
    log.info(
        "length pairs: %d train, %d val; the most frequent length scores %s", len(train), len(val), baseline
    )

    module = LengthEstimatorModule(
        text_encoder.sentence_dim,
        cfg.model,
        cfg.optim,
        cfg.label_smoothing,
        text_record(text_encoder, cfg.text),
        stage1_record(source),
        word_dim=text_encoder.word_dim,
    )
    collate = LengthBatch(datamodule.caption_cache, words=module.estimator.reads_words)
    run = TrackedRun(
        LENGTH,
        cfg_node,
        exclude=("stage1", "stage1_output_dir"),
        tags={
            **stage1_tags(source),
            "text_encoder": text_encoder.identity,
            "data.fingerprint": datamodule.data_fingerprint,
            "length.train_pairs": len(train),
            "length.val_pairs": len(val),
        },
        dataset=(cfg.data.name, cfg.data.root, datamodule.data_fingerprint),
        metrics=baseline,
        description=(
            f"Length estimator (caption -> codes) over {text_encoder.identity} embeddings "
            f"(pooling {cfg.model.pooling}), on the "
            "tokens of "
            f"`{source.reference}`; {len(train)} training pairs. "
            "`baseline/*`: always the most frequent length."
        ),
    )
    loaders = {
        "train_dataloaders": ResumableDataLoader(
            train,
            cfg.data.batch_size,
            shuffle=True,
            seed=cfg.seed,
            drop_last=len(train) > cfg.data.batch_size,
            collate_fn=collate,
        ),
        "val_dataloaders": ResumableDataLoader(
            val, cfg.data.batch_size, shuffle=False, seed=cfg.seed, collate_fn=collate
        ),
    }
    fit_started = time.perf_counter()
    result, trainer, logger = tracked_fit(run, cfg, module, run_target(cfg), [], loaders=loaders)
    result.metrics.update(baseline)  # logged at step 0
    log_final_metrics(
        result,
        trainer,
        logger,
        {"time/fit_s": time.perf_counter() - fit_started, "time/total_s": time.perf_counter() - started},
    )
    return result

"""Train the package's own text-motion evaluator (`train_evaluator(cfg)`; conf/train_evaluator.yaml).

It reads the dataset's captioned motions (TextMotionDataModule: normalized features, lengths, one
random caption and crop per item and epoch) and the cached sentence embeddings of the configured
frozen text encoder, and trains a ContrastiveEvaluator (mmm.evaluation.contrastive) with a
symmetric InfoNCE loss. The run is tracked like the other models: resolved config as params,
per-step loss, validation loss and in-batch retrieval accuracy, best/last checkpoints as
artifacts, tags naming the text encoder and the data fingerprint.

After training, the best checkpoint is scored on the TEST split by the standard protocol
(batches of 32 shuffled with a fixed seed, drop_last, one random caption per item, the length cut
to a multiple of 4, one unit shorter with probability 1/3): R-precision top-1/2/3 and the mean
matching distance, logged as `test/*`; the same with captions shuffled across items
(`baseline/shuffled_*`, about 1/32 top-1) shows what chance scores. Then the checkpoints are
registered in the MLflow Model Registry (a new version of `registry.name`, source
`runs:/<run_id>/checkpoints`, tagged with the data fingerprint, the text encoder identity and the
test numbers): the evaluator is the yardstick that promotion compares generators against.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

import lightning as L
import torch
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig
from torch.utils.data import Dataset

from mmm.config import to_object
from mmm.data.configs import DataConfig
from mmm.data.datamodule import TextMotionDataModule
from mmm.data.datasets import TextMotionDataset, collate_motions
from mmm.data.resumable import ResumableDataLoader
from mmm.evaluation.contrastive import (
    ContrastiveEvaluator,
    EvaluatorEmbedder,
    load_contrastive_evaluator,
    retrieval_metrics,
)
from mmm.evaluation.contrastive_module import ContrastiveEvaluatorModule
from mmm.evaluation.counterfactuals import counterfactual_ranking
from mmm.fingerprint import dataset_fingerprint
from mmm.kinds import EVALUATOR
from mmm.registry.versions import WEIGHTS_SHA256, freeze_weights
from mmm.text.counterfactuals import KINDS, counterfactual_captions
from mmm.text.encoders import build_text
from mmm.tracking import resolve_tracking_uri
from mmm.training.common import (
    TrackedRun,
    TrainResult,
    log_final_metrics,
    run_target,
    tag_run,
    text_record,
    tracked_fit,
)
from mmm.training.configs import EvaluatorTrainConfig

log = logging.getLogger(__name__)


@dataclass
class EvaluatorTrainResult(TrainResult):
    registered_model: str | None = None
    model_version: str | None = None
    data_fingerprint: str | None = None
    text_encoder: str | None = None


# ---------------------------------------------------------------------------------------- data


class CaptionedMotionCollator:
    """collate_motions plus the captions' cached sentence embeddings: {"motion" (B, T, D),
    "lengths" (B,), "sentence" (B, Ds), "captions", "names"}. With `counterfactuals` (kinds, see
    mmm.text.counterfactuals) also each caption's counterfactuals, the hard negatives:
    "counterfactual" (B, K, Ds) zero-padded and "counterfactual_mask" (B, K), K the most any caption
    has (0 when none has one). Picklable (loader workers)."""

    def __init__(self, caption_cache, counterfactuals: list[str] | tuple[str, ...] = ()):
        self.caption_cache = caption_cache
        self.counterfactuals = tuple(counterfactuals)

    def __call__(self, batch: list[dict]) -> dict:
        out = collate_motions(batch)
        out["sentence"] = self.caption_cache.lookup(out["captions"]).sentence
        if self.counterfactuals:
            variants = [counterfactual_captions(c, self.counterfactuals) for c in out["captions"]]
            K = max(map(len, variants))
            hard = torch.zeros(len(variants), K, out["sentence"].shape[-1])
            mask = torch.zeros(len(variants), K, dtype=torch.bool)
            flat = [v for vs in variants for v in vs]
            if flat:
                sentences = self.caption_cache.lookup(flat).sentence
                row = 0
                for i, vs in enumerate(variants):
                    hard[i, : len(vs)] = sentences[row : row + len(vs)]
                    mask[i, : len(vs)] = True
                    row += len(vs)
            out["counterfactual"], out["counterfactual_mask"] = hard, mask
        return out


class FixedOrder(Dataset):
    """`dataset` read in a fixed order, ignoring the epoch tag of the index: every validation
    sees the same pairs in the same batches."""

    def __init__(self, dataset: Dataset, order: list[int]):
        self.dataset, self.order = dataset, list(order)

    def __len__(self) -> int:
        return len(self.order)

    def __getitem__(self, index: int) -> dict:
        return self.dataset[self.order[index % len(self.order)]]


def protocol_dataset(items, mean, std, data: DataConfig, seed: int) -> TextMotionDataset:
    """Items as the evaluation protocol draws them: one random caption, the length cut to a
    multiple of unit_length (one unit shorter with probability 1/3), at a random offset; seeded."""
    return TextMotionDataset(
        items,
        mean,
        std,
        max_length=data.max_length,
        unit_length=data.unit_length,
        random_crop=True,
        seed=seed,
    )


def seeded_order(n: int, seed: int) -> list[int]:
    return torch.randperm(n, generator=torch.Generator().manual_seed(seed)).tolist()


@torch.no_grad()
def evaluate_retrieval(
    evaluator: ContrastiveEvaluator,
    dataset: Dataset,
    sentences_of: Callable[[list[str]], torch.Tensor],
    batch_size: int = 32,
    seed: int = 0,
    shuffle_captions: bool = False,
    device: str | torch.device = "cpu",
) -> dict[str, float]:
    """R-precision top-1/2/3 and matching distance of `evaluator` on `dataset` (items with
    "motion" normalized, "length", "caption"): the items in an order seeded by `seed`, batches of
    `batch_size` with the remainder dropped (a split smaller than one batch is one batch, with a
    warning). shuffle_captions: pair each motion with another item's caption (a seeded
    permutation over the evaluated items), what chance scores."""
    n = len(dataset)
    if n < 2:
        raise ValueError(f"retrieval needs at least 2 items, the split has {n}")
    if n < batch_size:
        log.warning(
            "the split has %d items, fewer than one batch of %d: scoring one batch of %d (easier than the "
            "protocol's)",
            n,
            batch_size,
            n,
        )
        batch_size = n
    order = seeded_order(n, seed)[: n // batch_size * batch_size]
    samples = [dataset[i] for i in order]
    captions = [s["caption"] for s in samples]
    if shuffle_captions:
        permutation = seeded_order(len(captions), seed + 1)
        captions = [captions[j] for j in permutation]
    evaluator = evaluator.to(device).eval()
    texts, motions = [], []
    for start in range(0, len(samples), batch_size):
        batch = collate_motions(samples[start : start + batch_size])
        motions.append(evaluator.embed_motions(batch["motion"].to(device), batch["lengths"]).cpu())
        texts.append(
            evaluator.embed_sentences(sentences_of(captions[start : start + batch_size]).to(device)).cpu()
        )
    scores = retrieval_metrics(texts, motions, top_k=3)
    return {**scores, "items": float(len(samples)), "batch_size": float(batch_size)}


# ---------------------------------------------------------------------------------------- registry


def register_evaluator(
    tracking_uri: str,
    name: str,
    run_id: str,
    tags: dict[str, object],
    description: str = "",
    checkpoint: str | None = None,
):
    """A new version of registered model `name` (created when missing); returns the ModelVersion.
    Its source is an immutable copy of `checkpoint` in the run (`registered/<name>-<sha256[:12]>/`,
    its digest tagged `weights.sha256`), or without one the run's checkpoints/ artifacts."""
    client = MlflowClient(tracking_uri)
    try:
        client.get_registered_model(name)
    except MlflowException:
        try:
            client.create_registered_model(
                name,
                tags={"mmm.kind": EVALUATOR.name},
                description=(
                    "Contrastive text-motion evaluators (mmm train evaluator): the yardstick generators are "
                    "promoted against."
                ),
            )
        except MlflowException as e:  # another process created it meanwhile
            if "RESOURCE_ALREADY_EXISTS" not in str(e.error_code):
                raise
    source = f"runs:/{run_id}/checkpoints"
    if checkpoint:
        source, digest = freeze_weights(client, run_id, checkpoint, name)
        tags = {**tags, WEIGHTS_SHA256: digest}
    return client.create_model_version(
        name,
        source=source,
        run_id=run_id,
        tags={k: "" if v is None else str(v) for k, v in tags.items()},
        description=description,
    )


# ---------------------------------------------------------------------------------------- training


def captions_to_embed(items: dict[str, list], hard_negative_kinds) -> list[str]:
    """The captions an evaluator run embeds: every caption of the splits ("train", "val", "test" ->
    MotionItems), then the counterfactuals it needs that are not among them: every kind of the test
    captions' (the ranking after training), the hard negatives' kinds of the train and val captions'."""
    captions = sorted({c.text for split in items.values() for item in split for c in item.captions})
    kinds = {"train": tuple(hard_negative_kinds), "val": tuple(hard_negative_kinds), "test": KINDS}
    variants = {
        v
        for split, split_kinds in kinds.items()
        if split_kinds
        for item in items[split]
        for c in item.captions
        for v in counterfactual_captions(c.text, split_kinds)
    }
    return captions + sorted(variants - set(captions))


def train_evaluator(cfg_node: DictConfig) -> EvaluatorTrainResult:
    cfg: EvaluatorTrainConfig = to_object(cfg_node)
    started = time.perf_counter()
    L.seed_everything(cfg.seed, workers=True)
    datamodule = TextMotionDataModule(cfg.data, seed=cfg.seed)
    datamodule.prepare_data()
    datamodule.setup()  # train, val and test items with the dataset's Mean/Std
    items = {split: datamodule.datasets[split].items for split in ("train", "val", "test")}
    mean, std = datamodule.mean, datamodule.std
    fingerprint = dataset_fingerprint(datamodule.root)

    cache_started = time.perf_counter()
    text_encoder, caption_cache = build_text(cfg.text)
    captions = captions_to_embed(items, cfg.loss.counterfactuals)
    counts = caption_cache.build(text_encoder, captions, progress=cfg.trainer.enable_progress_bar)
    cache_seconds = time.perf_counter() - cache_started
    log.info(
        "caption embeddings (%s): %d captions, %d newly encoded",
        text_encoder.identity,
        len(captions),
        counts["added"],
    )

    train = protocol_dataset(items["train"], mean, std, cfg.data, cfg.seed)
    val = FixedOrder(
        protocol_dataset(items["val"], mean, std, cfg.data, cfg.seed + 1),
        seeded_order(len(items["val"]), cfg.seed + 1),
    )
    val_batch = min(cfg.retrieval.batch_size, len(val))
    collate = CaptionedMotionCollator(caption_cache, cfg.loss.counterfactuals)

    text = text_record(text_encoder, cfg.text)
    data = {
        "name": cfg.data.name,
        "root": str(cfg.data.root),
        "fingerprint": fingerprint,
        "skeleton": cfg.data.skeleton,
        "fps": cfg.data.fps,
        "max_length": cfg.data.max_length,
        "unit_length": cfg.data.unit_length,
    }
    module = ContrastiveEvaluatorModule(
        cfg.data.feature_dim, text_encoder.sentence_dim, cfg.model, cfg.optim, cfg.loss, mean, std, text, data
    )
    run = TrackedRun(
        EVALUATOR,
        cfg_node,
        tags={
            "text_encoder": text_encoder.identity,
            "data.fingerprint": fingerprint,
            "data.name": cfg.data.name,
            "data.root": cfg.data.root,
            "evaluator.train_items": len(items["train"]),
            "evaluator.val_items": len(items["val"]),
            "evaluator.test_items": len(items["test"]),
        },
        dataset=(cfg.data.name, cfg.data.root, fingerprint),
        description=(
            f"The package's own text-motion evaluator on {cfg.data.name} ({fingerprint}), text encoder "
            f"{text_encoder.identity}: "
            "trained with InfoNCE, scored on the test split (`test/*`; `baseline/shuffled_*`: the same with "
            "shuffled captions)."
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
            num_workers=cfg.data.num_workers,
            persistent_workers=cfg.data.num_workers > 0,
        ),
        "val_dataloaders": ResumableDataLoader(
            val, val_batch, shuffle=False, seed=cfg.seed, drop_last=True, collate_fn=collate
        ),
    }
    fit_started = time.perf_counter()
    result, trainer, logger = tracked_fit(
        run,
        cfg,
        module,
        run_target(cfg),
        [],
        loaders=loaders,
        result_type=EvaluatorTrainResult,
        data_fingerprint=fingerprint,
        text_encoder=text_encoder.identity,
    )
    fit_seconds = time.perf_counter() - fit_started
    if not trainer.is_global_zero:
        return result

    # The model that gets registered: the best checkpoint (the last one when none was kept).
    test_started = time.perf_counter()
    checkpoint = result.best_checkpoint or result.last_checkpoint
    evaluator = load_contrastive_evaluator(checkpoint)[0] if checkpoint else module.evaluator.eval()
    test = protocol_dataset(items["test"], mean, std, cfg.data, cfg.retrieval.seed)

    def sentences_of(captions: list[str]) -> torch.Tensor:
        return caption_cache.lookup(captions).sentence

    scores = evaluate_retrieval(evaluator, test, sentences_of, cfg.retrieval.batch_size, cfg.retrieval.seed)
    chance = evaluate_retrieval(
        evaluator, test, sentences_of, cfg.retrieval.batch_size, cfg.retrieval.seed, shuffle_captions=True
    )
    evaluation = {f"test/{k}": v for k, v in scores.items()}
    # Does it read how often and how fast: the real test motion's own caption against the same
    # caption with its count or speed changed.
    embedder = EvaluatorEmbedder(evaluator, text_encoder=text_encoder, caption_cache=caption_cache)
    for kind, row in counterfactual_ranking(embedder, items["test"]).items():
        evaluation[f"test/counterfactual_{kind}_first"] = row["first"]
        evaluation[f"test/counterfactual_{kind}_captions"] = float(row["captions"])
    evaluation.update(
        {f"baseline/shuffled_{k}": v for k, v in chance.items() if k not in ("items", "batch_size")}
    )
    timing = {
        "time/caption_cache_s": cache_seconds,
        "time/fit_s": fit_seconds,
        "time/test_s": time.perf_counter() - test_started,
    }
    timing["time/total_s"] = time.perf_counter() - started
    log.info("test retrieval: %s; with shuffled captions: %s", scores, chance)
    log_final_metrics(result, trainer, logger, {**evaluation, **timing})
    if logger is not None:
        if cfg.registry.register and cfg.logger.log_checkpoints and result.best_checkpoint:
            tags = {
                "mmm.kind": EVALUATOR.name,
                "data.fingerprint": fingerprint,
                "data.name": cfg.data.name,
                "text_encoder": text_encoder.identity,
                "global_step": trainer.global_step,
                **{f"test.{k}": f"{v:.4f}" for k, v in scores.items() if k not in ("items", "batch_size")},
                "test.items": int(scores["items"]),
                "test.batch_size": int(scores["batch_size"]),
                "baseline.shuffled_r_precision_top1": f"{chance['r_precision_top1']:.4f}",
            }
            version = register_evaluator(
                resolve_tracking_uri(cfg.logger.tracking_uri),
                cfg.registry.name,
                logger.run_id,
                tags,
                description=(
                    f"{cfg.data.name} ({fingerprint}), text encoder {text_encoder.identity}: test "
                    "R-precision top-1/2/3 "
                    f"{scores['r_precision_top1']:.3f}/{scores['r_precision_top2']:.3f}/"
                    f"{scores['r_precision_top3']:.3f}, "
                    f"matching distance {scores['matching_distance']:.3f}"
                ),
                checkpoint=checkpoint,
            )
            result.registered_model, result.model_version = cfg.registry.name, str(version.version)
            tag_run(logger, {"registered_model": cfg.registry.name, "registered_version": version.version})
            log.info("registered %s version %s (%s)", cfg.registry.name, version.version, version.source)
    return result

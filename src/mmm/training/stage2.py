"""Stage 2: train the masked transformer on cached tokens (`mmm train stage2 [key=value ...]`).

The stage-1 model comes from `stage1=` (a checkpoint, an MLflow run id, a models:/ URI), or is
the newest finished stage-1 run when none is named.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import lightning as L
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig

from mmm.callbacks.adherence import AdherenceCurve
from mmm.callbacks.previews import GenerationPreview
from mmm.callbacks.weight_ema import WeightEMA, check_resume_ema
from mmm.config import ConfigError, to_object
from mmm.data.datamodule import TokenTextDataModule
from mmm.kinds import STAGE1_PARTS, STAGE2, STAGE2_PARTS
from mmm.resolve import registered_version
from mmm.text.encoders import build_text
from mmm.tokenizer.load import load_tokenizer
from mmm.tracking import resolve_tracking_uri, run_link, version_link
from mmm.training.common import (
    TrackedRun,
    TrainResult,
    run_target,
    text_record,
    tracked_fit,
)
from mmm.training.configs import Stage2Config
from mmm.transformer.module import MaskedTransformerModule, stage2_codebooks

log = logging.getLogger(__name__)


def check_codebook(checkpoint: Path, meta: dict, codebook_shape: list[int]) -> None:
    """Refuse to resume a transformer on a codebook of another shape; `meta`: the checkpoint's
    `read_checkpoint_meta`."""
    hp = meta["hyper_parameters"] or {}
    if list(hp.get("codebook_shape", codebook_shape)) != list(codebook_shape):
        raise ValueError(
            f"{checkpoint}: this transformer was trained on a codebook of shape {hp['codebook_shape']}, but "
            "the stage-1 model "
            f"has {codebook_shape}; resume with the stage-1 model it was trained with (stage1=...)"
        )


def check_stage1_identity(checkpoint: Path, meta: dict, source) -> None:
    """Refuse to resume a transformer on other stage-1 weights than it was trained on: a codebook
    of the same shape with other codes would silently change what every token means."""
    recorded = (meta["hyper_parameters"] or {}).get("stage1") or {}
    if recorded.get("identity") and recorded["identity"] != source.identity:
        raise ValueError(
            f"{checkpoint}: this transformer was trained on stage-1 model {recorded.get('reference', '?')} "
            f"(weights {recorded['identity']}), "
            f"but stage1= resolves to {source.reference} (weights {source.identity}); resume with "
            f"stage1={recorded.get('reference', '...')} "
            "(the model it was trained with), or start a new run without --resume"
        )


def prepare_stage2_data(cfg_node: DictConfig) -> TokenTextDataModule:
    """Resolve the stage-1 model, tokenize the dataset and cache the caption embeddings."""
    cfg: Stage2Config = to_object(cfg_node)
    tokenizer, source = load_tokenizer(
        cfg.stage1,
        resolve_tracking_uri(cfg.logger.tracking_uri),
        cfg.stage1_output_dir,
        cfg.stage1_experiment,
    )
    log.info("stage-1 model: %s (identity %s)", source.reference, source.identity)
    tokenizer_parts = bool(getattr(tokenizer.tokenizer, "part_aware", False))
    if tokenizer_parts != cfg.part_aware:
        raise ValueError(
            f"stage-1 model {source.reference} is "
            f"{'part-aware' if tokenizer_parts else 'a whole-body tokenizer'}, but this stage-2 config "
            f"trains {'the part-aware' if cfg.part_aware else 'the whole-body'} transformer; "
            + (
                f"use `mmm train {STAGE2_PARTS.name}` ({STAGE2_PARTS.train})"
                if tokenizer_parts
                else f"train one with `{STAGE1_PARTS.train}` or name it with stage1=..."
            )
        )
    text_encoder, caption_cache = build_text(cfg.text)
    datamodule = TokenTextDataModule(
        cfg.data,
        cfg.seed,
        tokenizer,
        source.identity,
        text_encoder,
        caption_cache,
        cfg.token_cache_dir,
        cfg.model.transformer.max_tokens,
        encoding=replace(tokenizer.encode_cfg, candidates=1) if cfg.token_encoding == "nearest" else None,
    )
    datamodule.source = source
    datamodule.prepare_data()
    return datamodule


def stage1_record(source) -> dict:
    """The stage-1 model a stage-2 model (or a length estimator) was trained on, as its checkpoint
    records it."""
    return {
        "reference": source.reference,
        "run_id": source.run_id,
        "identity": source.identity,
        "checkpoint": source.checkpoint,
    }


def stage1_tags(source) -> dict:
    """The stage-1 model as run tags (`stage1.reference`, `stage1.run_id`, `stage1.identity`)."""
    return {
        "stage1.reference": source.reference,
        "stage1.run_id": source.run_id,
        "stage1.identity": source.identity,
    }


def adherence_items(cfg: Stage2Config) -> list:
    """The fixed validation items of the adherence curve: `callbacks.adherence_captions` of the
    val split, evenly spread over it (none without labels/)."""
    wanted = cfg.callbacks.adherence_captions
    if wanted <= 0 or not (Path(cfg.data.root) / "labels").is_dir():
        return []
    items, _ = cfg.data.items("val")
    stride = max(1, len(items) // wanted)
    return items[::stride][:wanted]


ADHERENCE_MONITORS = ("val_adherence/ordered_rate", "val_adherence/rate")


def check_adherence_monitor(cfg: Stage2Config, curve_items: list) -> bool:
    """Whether best.ckpt is chosen by the adherence curve (callbacks.checkpoint.monitor names one of
    its overall figures); refused where the curve is not measured."""
    monitor = cfg.callbacks.checkpoint.monitor
    if not monitor.startswith("val_adherence/"):
        return False
    if monitor not in ADHERENCE_MONITORS:
        raise ConfigError(
            f"callbacks.checkpoint.monitor={monitor}: best.ckpt can follow the overall adherence only, "
            f"{' or '.join(ADHERENCE_MONITORS)} (with mode=max)"
        )
    if not curve_items:
        raise ConfigError(
            f"callbacks.checkpoint.monitor={monitor} needs the adherence curve, which is not measured here: "
            f"it needs a labelled whole-body dataset (labels/ in data.root={cfg.data.root}) and "
            f"callbacks.adherence_captions > 0 (is {cfg.callbacks.adherence_captions}); "
            "or monitor val/loss (mode=min)"
        )
    if cfg.callbacks.checkpoint.mode != "max":
        raise ConfigError(
            f"callbacks.checkpoint.monitor={monitor} is a share followed: set callbacks.checkpoint.mode=max"
        )
    return True


def train_stage2(cfg_node: DictConfig, resume: str | None = None) -> TrainResult:
    cfg: Stage2Config = to_object(cfg_node)
    L.seed_everything(cfg.seed, workers=True)
    datamodule = prepare_stage2_data(cfg_node)
    tokenizer, source, text_encoder = datamodule.tokenizer, datamodule.source, datamodule.text_encoder
    codebook, condition_codebook = stage2_codebooks(tokenizer)

    def check(checkpoint: Path, meta: dict) -> None:
        check_codebook(checkpoint, meta, list(codebook.shape))
        check_stage1_identity(checkpoint, meta, source)
        check_resume_ema(checkpoint, meta["weight_ema"], cfg.callbacks.weight_ema)

    target = run_target(cfg, resume, check)
    module = MaskedTransformerModule(
        codebook,
        cfg.model.transformer,
        cfg.optim,
        cfg.corruption,
        text_encoder.sentence_dim,
        text_encoder.word_dim,
        stage1_record(source),
        text_record(text_encoder, cfg.text),
        condition_codebook=condition_codebook,
    )
    callbacks = (
        [GenerationPreview(tokenizer, text_encoder, cfg.callbacks.preview_captions, cfg.seed)]
        if cfg.callbacks.preview_captions > 0
        else []
    )
    curve_items = adherence_items(cfg) if not cfg.part_aware else []
    by_adherence = check_adherence_monitor(cfg, curve_items)
    if curve_items:
        callbacks.append(
            AdherenceCurve(
                tokenizer, text_encoder, cfg.data.root, curve_items, cfg.seed, publish=by_adherence
            )
        )
    if cfg.callbacks.weight_ema:  # last: the previews and the curve above see the average
        callbacks.append(WeightEMA(cfg.callbacks.weight_ema))
    lineage = (
        stage1_lineage(source, resolve_tracking_uri(cfg.logger.tracking_uri)) if cfg.logger.enabled else {}
    )
    run = TrackedRun(
        STAGE2_PARTS if cfg.part_aware else STAGE2,
        cfg_node,
        model_cfg=cfg.model,
        # The stage-1 model is recorded once, resolved (tags below), not as the options that found it.
        exclude=("model.tokenizer", "stage1", "stage1_output_dir", "stage1_experiment"),
        tags={
            **stage1_tags(source),
            "stage1.version": lineage.get("version"),
            "text_encoder": text_encoder.identity,
            "data.fingerprint": datamodule.data_fingerprint,
        },
        dataset=(cfg.data.name, cfg.data.root, datamodule.data_fingerprint),
        description=(
            "Masked transformer "
            f"({'part-aware, ' if cfg.part_aware else ''}{cfg.model.transformer.num_layers} layers of "
            f"{cfg.model.transformer.embed_dim}) on the tokens of "
            f"{lineage.get('markdown', source.reference)} "
            f"(weights {source.identity}), text encoder {text_encoder.identity}, data {cfg.data.name} "
            f"({datamodule.data_fingerprint})."
        ),
    )
    result, _, _ = tracked_fit(run, cfg, module, target, callbacks, datamodule=datamodule)
    return result


def stage1_lineage(source, tracking_uri: str) -> dict:
    """The stage-1 model as links: its run, and the exact registered version a models:/ alias
    resolved to ({"version": "mmm-tokenizer/3", "markdown": ...})."""
    out, links = {}, []
    if source.reference.startswith("models:/"):
        version = registered_version(source.reference, tracking_uri)
        out["version"] = f"{version.name}/{version.version}"
        links.append(
            version_link(version.name, version.version)
            + (f" (`{source.reference}`)" if "@" in source.reference else "")
        )
    if source.run_id:
        try:
            experiment = MlflowClient(tracking_uri).get_run(source.run_id).info.experiment_id
            links.append("the stage-1 run " + run_link(experiment, source.run_id))
        except MlflowException:
            links.append(f"the stage-1 run {source.run_id}")
    out["markdown"] = ", ".join(links) if links else f"`{source.reference}`"
    return out

"""Stage 1: train the motion tokenizer (`mmm train stage1 [key=value ...] [--resume last|PATH]`)."""

from __future__ import annotations

from dataclasses import asdict

import lightning as L
from omegaconf import DictConfig

from mmm.callbacks.codebook import CodebookReset, CollapseMonitor
from mmm.callbacks.previews import CodebookUsagePlot, ReconstructionPreview
from mmm.config import to_object
from mmm.data.datamodule import TokenizerDataModule
from mmm.fingerprint import dataset_fingerprint
from mmm.kinds import STAGE1, STAGE1_PARTS
from mmm.tokenizer.module import TokenizerModule
from mmm.training.common import TrackedRun, TrainResult, run_target, tracked_fit
from mmm.training.configs import (
    Stage1Config,
)


def build_callbacks(cfg: Stage1Config) -> list[L.Callback]:
    cb = cfg.callbacks
    callbacks: list[L.Callback] = [
        CodebookReset(cb.reset_every_n_steps),
        CollapseMonitor(**asdict(cb.collapse)),
    ]
    if cb.preview_clips > 0:
        callbacks.append(ReconstructionPreview(cb.preview_clips))
    if cb.usage_plot:
        callbacks.append(CodebookUsagePlot())
    return callbacks


def train_stage1(cfg_node: DictConfig, resume: str | None = None) -> TrainResult:
    """Train a tokenizer as configured; `resume` = "last" or a checkpoint path continues a run
    (a checkpoint outside this stage's run folders is only read: the run goes on in a new folder)."""
    cfg: Stage1Config = to_object(cfg_node)
    cfg.trainer.max_steps += cfg.refine.steps  # the fit: the whole tokenizer, then the decoder alone
    L.seed_everything(cfg.seed, workers=True)
    target = run_target(cfg, resume)
    datamodule = TokenizerDataModule(
        cfg.data,
        seed=cfg.seed,
        normalization=cfg.normalization,
        start_windows=cfg.refine.start_windows if cfg.refine.steps > 0 else 0.0,
    )
    datamodule.prepare_data()
    datamodule.setup("fit")
    module = TokenizerModule(
        cfg.data.feature_dim,
        cfg.model.tokenizer,
        cfg.optim,
        cfg.loss,
        datamodule.mean,
        datamodule.std,
        cfg.refine,
        cfg.encode,
    )
    fingerprint = dataset_fingerprint(cfg.data.root)
    tokenizer = cfg.model.tokenizer
    run = TrackedRun(
        STAGE1_PARTS if tokenizer.part_aware else STAGE1,
        cfg_node,
        exclude=("model.transformer",),
        model_cfg=cfg.model,
        tags={"data.name": cfg.data.name, "data.root": cfg.data.root, "data.fingerprint": fingerprint},
        dataset=(cfg.data.name, cfg.data.root, fingerprint),
        description=f"Tokenizer ({'part-aware, ' if tokenizer.part_aware else ''}"
        f"{tokenizer.num_codes} codes of "
        f"{tokenizer.code_dim} dims, width {tokenizer.width}) on {cfg.data.name} ({fingerprint}), "
        f"normalized with the {cfg.normalization.statistics} statistics.",
    )
    result, _, _ = tracked_fit(run, cfg, module, target, build_callbacks(cfg), datamodule=datamodule)
    return result

"""Callbacks that let people look at a run: rendered motions and codebook usage, as MLflow artifacts."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import lightning as L
import numpy as np
from lightning.pytorch.loggers import MLFlowLogger

log = logging.getLogger(__name__)


def _mlflow_loggers(trainer) -> list[MLFlowLogger]:
    return [lg for lg in trainer.loggers if isinstance(lg, MLFlowLogger)]


class ReconstructionPreview(L.Callback):
    """At each validation, a GIF of a few validation clips, reference beside reconstruction,
    logged as `previews/reconstruction_step<step>.gif` (rank 0)."""

    def __init__(self, num_clips: int = 3, size: int = 240):
        self.num_clips, self.size = num_clips, size

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        batch = getattr(pl_module, "preview_batch", None)
        if not trainer.is_global_zero or batch is None or trainer.sanity_checking:
            return
        loggers = _mlflow_loggers(trainer)
        if not loggers:
            return
        from mmm.render import render_gif

        motions, captions = [], []
        names = batch.get("names") or [str(i) for i in range(len(batch["lengths"]))]
        for i in range(min(self.num_clips, len(batch["lengths"]))):
            n = int(batch["lengths"][i])
            motions += [batch["reference"][i, :n].numpy(), batch["reconstruction"][i, :n].numpy()]
            captions += [f"{names[i]} reference", f"{names[i]} reconstruction"]
        with tempfile.TemporaryDirectory() as tmp:
            path = render_gif(motions, Path(tmp) / f"reconstruction_step{trainer.global_step:07d}.gif", captions=captions, size=(self.size, self.size))
            for lg in loggers:
                lg.experiment.log_artifact(lg.run_id, str(path), "previews")


def usage_histogram_png(counts: np.ndarray, out_path: Path, title: str) -> Path:
    """Bar chart of code usage sorted from most to least used, with the active count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = np.sort(counts)[::-1]
    fig, ax = plt.subplots(figsize=(7, 3), dpi=100)
    ax.bar(np.arange(len(order)), order, width=1.0, color="#3b6ea8")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_xlabel("codes, most used first")
    ax.set_ylabel("EMA assignment count")
    active = int((counts > 1e-3).sum())
    ax.set_title(f"{title}: {active}/{len(counts)} codes with EMA count > 0.001")
    fig.tight_layout()
    fig.savefig(out_path)
    plt.close(fig)
    return out_path


class CodebookUsagePlot(L.Callback):
    """At each validation, a histogram of each codebook's EMA counts, `codebook/usage_step<step>.png`
    (`codebook/<part>/usage_step<step>.png` for each codebook of a part-aware tokenizer)."""

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        if not trainer.is_global_zero or trainer.sanity_checking:
            return
        loggers = _mlflow_loggers(trainer)
        if not loggers:
            return
        step = trainer.global_step
        for name, quantizer in pl_module.quantizers.items():
            counts = quantizer.ema_count.detach().cpu().numpy()
            with tempfile.TemporaryDirectory() as tmp:
                title = f"{name} codebook, step {step}" if name else f"step {step}"
                path = usage_histogram_png(counts, Path(tmp) / f"usage_step{step:07d}.png", title)
                for lg in loggers:
                    lg.experiment.log_artifact(lg.run_id, str(path), f"codebook/{name}" if name else "codebook")


class GenerationPreview(L.Callback):
    """At each validation of stage 2, a few validation captions generated at their reference's
    length, beside the reference (decoded from its own codes), logged as
    `previews/generation_step<step>.gif` (rank 0). A part-aware model shows the reference's lower
    body with an upper body generated from the caption (half the lower-body codes hidden)."""

    def __init__(self, tokenizer, text_encoder, num_captions: int = 3, seed: int = 0, size: int = 240):
        self.tokenizer, self.text_encoder = tokenizer, text_encoder
        self.num_captions, self.seed, self.size = num_captions, seed, size

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        batch = getattr(pl_module, "preview_batch", None)
        if not trainer.is_global_zero or batch is None or trainer.sanity_checking or self.num_captions <= 0:
            return
        loggers = _mlflow_loggers(trainer)
        if not loggers:
            return
        from mmm.generation.model import TextToMotion
        from mmm.generation.upper_body import DEFAULT_LOWER_MASK
        from mmm.render import render_gif

        training = pl_module.transformer.training
        model = TextToMotion(self.tokenizer, pl_module.transformer, self.text_encoder, {}, device=pl_module.device)
        try:
            n = min(self.num_captions, len(batch["captions"]))
            codes = [batch["tokens"][i, : int(batch["lengths"][i])].numpy() for i in range(n)]
            frames = [min(max(len(c) * model.unit, model.min_frames), model.max_frames) for c in codes]
            reference_features = model.decode(codes)
            references = [model.to_joints(f) for f in reference_features]
            if model.part_aware:  # the reference's lower body, a new upper body from its caption
                generated = [model.edit_upper_body(f, c, lower_mask=DEFAULT_LOWER_MASK, seed=self.seed).joints[0]
                             for f, c in zip(reference_features, batch["captions"][:n])]
            else:
                generated = model.generate(list(batch["captions"][:n]), frames, seed=self.seed).joints
        finally:
            pl_module.transformer.train(training)
        motions, captions = [], []
        for i in range(n):
            motions += [references[i], generated[i]]
            captions += [f"reference: {batch['captions'][i]}", f"{'new upper body' if model.part_aware else 'generated'}: {batch['captions'][i]}"]
        with tempfile.TemporaryDirectory() as tmp:
            path = render_gif(motions, Path(tmp) / f"generation_step{trainer.global_step:07d}.gif", captions=captions, size=(self.size, self.size))
            for lg in loggers:
                lg.experiment.log_artifact(lg.run_id, str(path), "previews")

"""Callbacks that let people look at a run: rendered motions and codebook usage, logged to MLflow.

Motion previews are logged twice at each validation: as an image with the step
(`previews/<kind>` in the run's Images, with a step slider: each clip's reference above its
reconstruction or generation, a few frames each, captions and step written on it), and as a GIF
artifact (`previews/<kind>_step<step>.gif`: references in the top row, the model's output under
each).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import lightning as L
import numpy as np
from lightning.pytorch.loggers import MLFlowLogger
from matplotlib.figure import Figure
from PIL import Image

from mmm.generation.model import TextToMotion
from mmm.generation.upper_body import DEFAULT_LOWER_MASK
from mmm.render import contact_sheet, render_gif

log = logging.getLogger(__name__)


def _mlflow_loggers(trainer) -> list[MLFlowLogger]:
    return [lg for lg in trainer.loggers if isinstance(lg, MLFlowLogger)]


def log_preview(
    trainer,
    kind: str,
    references: list,
    outputs: list,
    reference_captions: list[str],
    output_captions: list[str],
    size: int = 320,
    frame_size: int = 160,
    num_frames: int = 6,
) -> None:
    """Log `previews/<kind>` (an image with the step, for the slider) and
    `previews/<kind>_step<step>.gif` (references above outputs) to every MLflow logger (rank 0)."""
    step = trainer.global_step
    loggers = _mlflow_loggers(trainer)
    if not loggers or not references:
        return
    ref_caps = [f"step {step} · {c}" for c in reference_captions]
    out_caps = [f"step {step} · {c}" for c in output_captions]
    rows, row_caps = [], []
    for ref, out, rc, oc in zip(references, outputs, ref_caps, out_caps):
        rows += [ref, out]
        row_caps += [rc, oc]
    sheet = contact_sheet(rows, row_caps, num_frames=num_frames, size=(frame_size, frame_size))
    with tempfile.TemporaryDirectory() as tmp:
        gif = render_gif(
            list(references) + list(outputs),
            Path(tmp) / f"{kind}_step{step:07d}.gif",
            captions=ref_caps + out_caps,
            size=(size, size),
            columns=len(references),
        )
        for lg in loggers:
            lg.experiment.log_image(lg.run_id, sheet, key=f"previews/{kind}", step=step)
            lg.experiment.log_artifact(lg.run_id, str(gif), "previews")


class ReconstructionPreview(L.Callback):
    """At each validation, a few validation clips: each reference above its reconstruction
    (`previews/reconstruction` image with the step, and a GIF), rank 0."""

    def __init__(self, num_clips: int = 3, size: int = 320):
        self.num_clips, self.size = num_clips, size

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        batch = getattr(pl_module, "preview_batch", None)
        if not trainer.is_global_zero or batch is None or trainer.sanity_checking:
            return
        loggers = _mlflow_loggers(trainer)
        if not loggers:
            return
        names = batch.get("names") or [str(i) for i in range(len(batch["lengths"]))]
        count = min(self.num_clips, len(batch["lengths"]))
        lengths = [int(batch["lengths"][i]) for i in range(count)]
        log_preview(
            trainer,
            "reconstruction",
            [batch["reference"][i, :n].numpy() for i, n in enumerate(lengths)],
            [batch["reconstruction"][i, :n].numpy() for i, n in enumerate(lengths)],
            [f"clip {names[i]}: reference" for i in range(count)],
            [f"clip {names[i]}: reconstruction" for i in range(count)],
            self.size,
        )


def usage_histogram_png(counts: np.ndarray, out_path: Path, title: str) -> Path:
    """Bar chart of code usage sorted from most to least used, with the active count (drawn
    without pyplot: no GUI backend, no global figure state)."""
    order = np.sort(counts)[::-1]
    fig = Figure(figsize=(7, 3), dpi=100)
    ax = fig.subplots()
    # One filled step outline, not a bar per code: the same picture, 0.16 s instead of 0.63 s at 512 codes.
    ax.stairs(order, np.arange(len(order) + 1), fill=True, color="#3b6ea8")
    ax.set_xlim(0, len(order))
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_xlabel("codes, most used first")
    ax.set_ylabel("EMA assignment count")
    active = int((counts > 1e-3).sum())
    ax.set_title(f"{title}: {active}/{len(counts)} codes with EMA count > 0.001")
    fig.tight_layout()
    fig.savefig(out_path)
    return out_path


class CodebookUsagePlot(L.Callback):
    """At each validation, a histogram of each codebook's EMA counts: the image `codebook/usage` with
    the step (`codebook/<part>/usage` for each codebook of a part-aware tokenizer) and the artifact
    `codebook/usage_step<step>.png`."""

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
                key = f"codebook/{name}/usage" if name else "codebook/usage"
                for lg in loggers:
                    with Image.open(path) as image:
                        lg.experiment.log_image(lg.run_id, image.convert("RGB"), key=key, step=step)
                    lg.experiment.log_artifact(
                        lg.run_id, str(path), f"codebook/{name}" if name else "codebook"
                    )


class GenerationPreview(L.Callback):
    """At each validation of stage 2, a few validation captions generated at their reference's
    length, beside the reference (decoded from its own codes), logged as
    `previews/generation` (image with the step) and a GIF (rank 0). A part-aware model shows the
    reference's lower body with an upper body generated from the caption (half the lower-body
    codes hidden)."""

    def __init__(self, tokenizer, text_encoder, num_captions: int = 3, seed: int = 0, size: int = 320):
        self.tokenizer, self.text_encoder = tokenizer, text_encoder
        self.num_captions, self.seed, self.size = num_captions, seed, size

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        batch = getattr(pl_module, "preview_batch", None)
        if not trainer.is_global_zero or batch is None or trainer.sanity_checking or self.num_captions <= 0:
            return
        loggers = _mlflow_loggers(trainer)
        if not loggers:
            return
        training = pl_module.transformer.training
        model = TextToMotion(
            self.tokenizer, pl_module.transformer, self.text_encoder, {}, device=pl_module.device
        )
        try:
            n = min(self.num_captions, len(batch["captions"]))
            codes = [batch["tokens"][i, : int(batch["lengths"][i])].numpy() for i in range(n)]
            frames = [min(max(len(c) * model.unit, model.min_frames), model.max_frames) for c in codes]
            reference_features = model.decode(codes)
            references = [model.to_joints(f) for f in reference_features]
            if model.part_aware:  # the reference's lower body, a new upper body from its caption
                generated = [
                    model.edit_upper_body(f, c, lower_mask=DEFAULT_LOWER_MASK, seed=self.seed).joints[0]
                    for f, c in zip(reference_features, batch["captions"][:n])
                ]
            else:
                generated = model.generate(list(batch["captions"][:n]), frames, seed=self.seed).joints
        finally:
            pl_module.transformer.train(training)
        kind = "new upper body" if model.part_aware else "generated"
        log_preview(
            trainer,
            "generation",
            references,
            list(generated),
            [f"reference: {c}" for c in batch["captions"][:n]],
            [f"{kind}: {c}" for c in batch["captions"][:n]],
            self.size,
        )

"""The paper's editing benchmarks: `mmm evaluate task=inbetween|outpaint|prefix|suffix|upper-body|long`.

Every task is scored by the replicated text-to-motion protocol (protocol.py: the same batches,
crops, seeds and intervals), with the batch's motions produced by an edit instead of generation:

- temporal tasks (the paper's temporal-editing table, MDM's protocol): each real test crop keeps
  some frames and the rest is generated from its caption, in one batched edit
  (`TextToMotion.edit_batch`). inbetween keeps the first and last 25% and generates the middle
  50%; outpaint keeps the middle 50% and generates the first and last 25%; prefix keeps the first
  50% and generates the rest; suffix keeps the last 50% and generates the first 50%. Fractions are
  `EditingConfig`'s; frame bounds are rounded to the tokenizer's 4-frame unit, so the kept frames
  are exactly the kept codes' frames. `with_text=False` generates them without the caption (the
  method's motion completion without text: the unconditional branch), logged as
  edit/<task>-without-text/...; R-Precision then says how much of the caption the kept frames
  alone carry into the completion.
- upper-body (the upper-body editing table; part-aware models): the lower body of each real crop
  is kept, the upper body generated from its caption, for every lower-body mask of the ablation
  sweep (`lower_masks`), one table row each, and a plot.
- long: `long_prompts` consecutive captions of a batch become one long motion
  (`TextToMotion.generate_long`); each segment, cut at the returned bounds, is scored against the
  real motion of its caption.

MultiModality is not measured for edits (an edit of one real motion has no set of generations per
caption to compare): "-" in the tables.

Exactness of the kept part (temporal tasks): over the kept frames, the joint difference between
the edited motion and (a) the source crop, (b) the source's own tokenizer reconstruction (mean and
max over frames and joints, mm). Each frame's pose is recovered on its own (`recover_from_ric` of
a one-frame motion: the pose at the origin, facing +Z), so a small velocity difference at the
boundary does not carry a drift through every later kept frame. (b) is what the method can
guarantee: the kept codes are the source's, and only the decoder's receptive field near a
generated frame differs; "far" is the same over kept frames at least `far_frames` from any
generated frame. (a) adds the tokenizer's own error, given too (reconstruction against source).
Upper body: the lower-body joints' global positions (the whole motion recovered) against the
source reconstruction and the source.

On labelled data (a `labels/` folder: the synthetic dataset), a separate pass over the split
(each item from its first frame, at most `adherence_max_items`) checks what the edit generated:
the item's label parts that a generated frame span covers (`parts_in_span`) are checked with the
synthetic checker on the edited motion; an edit whose generated spans cover no part is counted as
unchecked, never dropped silently. The same parts checked on the real motion give the reference.
The whole edited motion against the item's whole label is reported too. Upper body: the existing
`upper_body_adherence` (the requested upper action, the source's lower action, both) per lower
mask. Long: each segment's parts on the long motion.
"""

from __future__ import annotations

import json
import math
import time
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from mmm.data.humanml3d import MotionItem
from mmm.data.synthetic.adherence import check_motion
from mmm.evaluation.adherence import item_parts, parts_in_span
from mmm.evaluation.configs import EditingConfig, ProtocolConfig
from mmm.evaluation.protocol import METRICS, evaluate_text_to_motion, results_table
from mmm.evaluation.upper_body import lower_body_sources, upper_body_adherence
from mmm.generation.settings import SamplingConfig
from mmm.motion.parts import LOWER_JOINTS

TEMPORAL_TASKS = ("inbetween", "outpaint", "prefix", "suffix")
EDITING_TASKS = (*TEMPORAL_TASKS, "upper-body", "long")
TASKS = ("text2motion", *EDITING_TASKS)
PLOT_FILE = "upper_body_lower_mask.png"


def task_label(task: str, cfg: EditingConfig) -> str:
    """The task's name in metric keys and run names: `<task>-without-text` for a text-free temporal edit."""
    return task if cfg.with_text or task not in TEMPORAL_TASKS else f"{task}-without-text"


def _to_unit(x: float, unit: int) -> int:
    """x frames rounded to the nearest multiple of `unit` (halves up)."""
    return int(math.floor(x / unit + 0.5)) * unit


def keep_ranges(task: str, frames: int, cfg: EditingConfig, unit: int = 4) -> list[tuple[int, int]]:
    """The kept frame ranges [a, b) of a `frames`-long motion for a temporal task, on the `unit`
    grid, with at least one unit kept and one generated per generated span.

    80 frames: inbetween [(0, 20), (60, 80)], outpaint [(20, 60)], prefix [(0, 40)], suffix [(40, 80)]."""
    if frames < 3 * unit or frames % unit:
        raise ValueError(
            f"a temporal edit needs a multiple of {unit} frames, at least {3 * unit}; got {frames}"
        )
    if task == "inbetween":
        k = min(max(_to_unit(cfg.inbetween_keep * frames, unit), unit), (frames - unit) // 2 // unit * unit)
        return [(0, k), (frames - k, frames)]
    if task == "outpaint":
        kept = min(max(_to_unit(cfg.outpaint_keep * frames, unit), unit), frames - 2 * unit)
        start = min(max(_to_unit((frames - kept) / 2, unit), unit), frames - unit - kept)
        return [(start, start + kept)]
    if task in ("prefix", "suffix"):
        share = cfg.prefix_keep if task == "prefix" else cfg.suffix_keep
        k = min(max(_to_unit(share * frames, unit), unit), frames - unit)
        return [(0, k)] if task == "prefix" else [(frames - k, frames)]
    raise ValueError(f"task={task!r} is not a temporal edit; choose from {', '.join(TEMPORAL_TASKS)}")


def generated_spans(kept: list[tuple[int, int]], frames: int) -> list[tuple[int, int]]:
    """The frame ranges [a, b) of a `frames`-long motion outside the kept ranges."""
    spans, cursor = [], 0
    for a, b in sorted(kept):
        if a > cursor:
            spans.append((cursor, a))
        cursor = max(cursor, b)
    if cursor < frames:
        spans.append((cursor, frames))
    return spans


def _poses(model, features: np.ndarray) -> np.ndarray:
    """(T, J, 3): each frame's pose recovered on its own (at the origin, facing +Z) from (T, D)."""
    return model.to_joints(features[:, None])[:, 0]


class _Extremes:
    """Running mean and max of distances (mm)."""

    def __init__(self):
        self.total, self.count, self.max = 0.0, 0, 0.0

    def add(self, values: np.ndarray) -> None:
        if values.size:
            self.total += float(values.sum())
            self.count += int(values.size)
            self.max = max(self.max, float(values.max()))

    def result(self) -> dict:
        return {
            "mean": self.total / self.count if self.count else float("nan"),
            "max": self.max if self.count else float("nan"),
        }


class KeptExactness:
    """Joint differences over the kept frames of temporal edits (the module's docstring): the edit
    against the source ("source") and against the source's reconstruction ("reconstruction"), the
    latter also over kept frames at least `far_frames` from a generated frame ("reconstruction_far"),
    and the reconstruction against the source ("tokenizer")."""

    def __init__(self, model, far_frames: int):
        self.model, self.far_frames = model, far_frames
        self.scale = model.skeleton.unit_scale * 1000.0
        self.stats = {k: _Extremes() for k in ("source", "reconstruction", "reconstruction_far", "tokenizer")}
        self.frames = self.frames_far = 0

    def add(
        self, sources: list[np.ndarray], edited: list[np.ndarray], kept: list[list[tuple[int, int]]]
    ) -> None:
        """sources, edited: (T_i, D) un-normalized each; kept: each one's kept frame ranges."""
        recon = self.model.decode(self.model.encode_motions(sources))
        for source, out, rec, ranges in zip(sources, edited, recon, kept):
            T = out.shape[0]
            mask = np.zeros(T, dtype=bool)
            for a, b in ranges:
                mask[a:b] = True
            generated = np.flatnonzero(~mask)
            frames = np.flatnonzero(mask)
            distance = np.abs(frames[:, None] - generated[None]).min(1)
            p_out, p_src, p_rec = (_poses(self.model, x[:T][frames]) for x in (out, source, rec))
            d = lambda a, b: np.linalg.norm(a - b, axis=-1) * self.scale  # noqa: E731 (frames, joints)
            self.stats["source"].add(d(p_out, p_src))
            to_recon = d(p_out, p_rec)
            self.stats["reconstruction"].add(to_recon)
            self.stats["reconstruction_far"].add(to_recon[distance >= self.far_frames])
            self.frames_far += int((distance >= self.far_frames).sum())
            self.stats["tokenizer"].add(d(p_rec, p_src))
            self.frames += len(frames)

    def result(self) -> dict:
        return {
            **{k: v.result() for k, v in self.stats.items()},
            "far_frames": self.far_frames,
            "frames_far": self.frames_far,
            "frames": self.frames,
        }


class LowerBodyExactness:
    """Upper-body edits: the lower-body joints' global positions (whole motion recovered) of the
    edit against the source's reconstruction and against the source (mm)."""

    def __init__(self, model):
        self.model = model
        self.scale = model.skeleton.unit_scale * 1000.0
        self.stats = {k: _Extremes() for k in ("reconstruction", "source")}

    def add(self, source: np.ndarray, edited: np.ndarray) -> None:
        T = edited.shape[0]
        rec = self.model.decode([self.model.encode_motion(source)])[0][:T]
        lower = list(LOWER_JOINTS)
        j_out, j_rec, j_src = (self.model.to_joints(x[:T])[:, lower] for x in (edited, rec, source))
        self.stats["reconstruction"].add(np.linalg.norm(j_out - j_rec, axis=-1) * self.scale)
        self.stats["source"].add(np.linalg.norm(j_out - j_src, axis=-1) * self.scale)

    def result(self) -> dict:
        return {k: v.result() for k, v in self.stats.items()}


class Smoothness:
    """Long sequences: mean joint acceleration (m/s^2) over the transition frames, over the
    segments' frames and their ratio (> 1: the transitions jerk); the same at the hard cuts of the
    segments concatenated without transitions (4 frames either side of each cut) for comparison;
    seconds of generation per minute of motion."""

    def __init__(self, model):
        self.model = model
        self.acc = {k: _Extremes() for k in ("transition", "segment", "cut", "cut_segment")}
        self.seconds, self.frames = 0.0, 0

    def _acceleration(self, features: np.ndarray) -> np.ndarray:
        """(T,) mean joint acceleration per frame (0 at the first and last frame)."""
        joints = self.model.to_joints(features) * self.model.skeleton.unit_scale
        acc = np.zeros(len(joints))
        acc[1:-1] = (
            np.linalg.norm(joints[2:] - 2 * joints[1:-1] + joints[:-2], axis=-1).mean(-1) * self.model.fps**2
        )
        return acc

    def add(self, out, segments_codes: list[np.ndarray]) -> None:
        """out: a generate_long result; segments_codes: its segments' own codes."""
        features, bounds, unit = out.features[0], out.segments, self.model.unit
        acc = self._acceleration(features)
        inside = np.zeros(len(acc), dtype=bool)
        for a, b in bounds:
            inside[a + 1 : b - 1] = True  # the second difference reaches one frame past each end
        between = np.zeros(len(acc), dtype=bool)
        for (_, b), (a, _) in zip(bounds[:-1], bounds[1:]):
            between[b:a] = True
        self.acc["transition"].add(acc[between])
        self.acc["segment"].add(acc[inside & ~between])
        cut = self._acceleration(self.model.decode([np.concatenate(segments_codes)])[0])
        near = np.zeros(len(cut), dtype=bool)
        for end in np.cumsum([len(c) * unit for c in segments_codes])[:-1]:
            near[end - unit : end + unit] = True
        self.acc["cut"].add(cut[near])
        self.acc["cut_segment"].add(cut[1:-1][~near[1:-1]])
        self.seconds += out.seconds["total"]
        self.frames += features.shape[0]

    def result(self) -> dict:
        mean = {k: v.result()["mean"] for k, v in self.acc.items()}
        minutes = self.frames / self.model.fps / 60.0
        return {
            "transition_acceleration": mean["transition"],
            "segment_acceleration": mean["segment"],
            "transition_ratio": mean["transition"] / mean["segment"],
            "cut_ratio": mean["cut"] / mean["cut_segment"],
            "seconds_per_minute": self.seconds / minutes if minutes else float("nan"),
        }


# -- producers: how each protocol batch's motions are made ----------------------------------------
class TemporalEdits:
    """The protocol's producer for a temporal task: one batched edit of the batch's real crops."""

    def __init__(self, model, task: str, cfg: EditingConfig, sampling: SamplingConfig):
        self.model, self.task, self.cfg, self.sampling = model, task, cfg, sampling
        self.exactness = KeptExactness(model, cfg.far_frames)

    def __call__(
        self, texts: list[str], lengths: list[int], real: torch.Tensor, seed: int
    ) -> list[np.ndarray]:
        sources = [real[i, :n].numpy() for i, n in enumerate(lengths)]
        kept = [keep_ranges(self.task, n, self.cfg, self.model.unit) for n in lengths]
        texts = texts if self.cfg.with_text else [None] * len(texts)
        out = self.model.edit_batch(sources, kept, texts, self.sampling, seed, check_lengths=False)
        self.exactness.add(sources, out.features, kept)
        return out.features


class UpperBodyEdits:
    """The protocol's producer for upper-body edits at one lower-body mask (one edit per crop:
    `edit_upper_body` takes one source at a time)."""

    def __init__(self, model, lower_mask: float, sampling: SamplingConfig):
        self.model, self.lower_mask, self.sampling = model, lower_mask, sampling
        self.exactness = LowerBodyExactness(model)

    def __call__(
        self, texts: list[str], lengths: list[int], real: torch.Tensor, seed: int
    ) -> list[np.ndarray]:
        out = []
        for i, (text, n) in enumerate(zip(texts, lengths)):
            source = real[i, :n].numpy()
            edited = self.model.edit_upper_body(
                source,
                text,
                lower_mask=self.lower_mask,
                sampling=self.sampling,
                seed=seed + i,
                check_lengths=False,  # the protocol's crops may be one unit below the minimum
            ).features[0]
            self.exactness.add(source, edited)
            out.append(edited)
        return out


class LongSequences:
    """The protocol's producer for long sequences: each `long_prompts` consecutive captions of the
    batch become one long motion, cut back into its segments."""

    def __init__(self, model, cfg: EditingConfig, sampling: SamplingConfig):
        self.model, self.cfg, self.sampling = model, cfg, sampling
        self.smoothness = Smoothness(model)

    def __call__(
        self, texts: list[str], lengths: list[int], real: torch.Tensor, seed: int
    ) -> list[np.ndarray]:
        out = []
        k = self.cfg.long_prompts
        for g in range(0, len(texts), k):
            result = self.model.generate_long(
                texts[g : g + k],
                lengths[g : g + k],
                self.sampling,
                seed + g,
                self.cfg.transition_codes,
                self.cfg.context_codes,
                check_lengths=False,
            )
            features, sequence, unit = result.features[0], result.codes[0], self.model.unit
            out += [features[a:b] for a, b in result.segments]
            self.smoothness.add(result, [sequence[a // unit : b // unit] for a, b in result.segments])
        return out


# -- labelled adherence ---------------------------------------------------------------------------
def _labelled(root: Path, items: list[MotionItem], model, max_items: int | None):
    """(item, frames, its parts in its frame indices or [] when it has no label) per item."""
    out = []
    for item in items[: max_items or len(items)]:
        path = root / "labels" / f"{item.motion_id}.json"
        frames = min(item.length, model.max_frames) // model.unit * model.unit
        parts = (
            parts_in_span(item_parts(item, json.loads(path.read_text())), 0, frames) if path.exists() else []
        )
        out.append((item, frames, parts))
    return out


def _shifted(parts: list[dict], offset: int) -> list[dict]:
    return [{**p, "start": p["start"] + offset, "end": p["end"] + offset} for p in parts]


def temporal_adherence(
    model,
    root: Path,
    items: list[MotionItem],
    task: str,
    cfg: EditingConfig,
    sampling: SamplingConfig,
    seed: int = 0,
    batch_size: int = 32,
    max_items: int | None = None,
) -> dict:
    """Adherence of what a temporal edit generated (module docstring), each item edited from its
    first frame at its length (a multiple of 4, at most the model's maximum): "rate" of the
    edits with a checkable generated part, "real_rate" of the same parts on the real motions,
    "count", "unchecked" (no label part inside a generated span), "whole_rate"/"whole_count" (the
    whole edited motion against the item's label), "per_action" {actions: (passed, total)}."""
    plans = []
    for item, frames, parts in _labelled(root, items, model, max_items):
        if frames < 3 * model.unit:
            plans.append(None)  # too short to keep and generate anything: counted as unchecked
            continue
        kept = keep_ranges(task, frames, cfg, model.unit)
        edited = [
            p for a, b in generated_spans(kept, frames) for p in _shifted(parts_in_span(parts, a, b), a)
        ]
        plans.append((item, frames, parts, kept, edited))
    passed, real_passed, whole = [], [], []
    per_action: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    unchecked = sum(p is None or not p[4] for p in plans)
    todo = [p for p in plans if p is not None and (p[4] or p[2])]
    for b in range(0, len(todo), batch_size):
        chunk = todo[b : b + batch_size]
        out = model.edit_batch(
            [item.features[:frames] for item, frames, *_ in chunk],
            [kept for *_, kept, _ in chunk],
            [item.captions[0].text if cfg.with_text else None for item, *_ in chunk],
            sampling,
            seed + b,
            check_lengths=False,
        )
        for joints, (item, frames, parts, _, edited) in zip(out.joints, chunk):
            joints = np.asarray(joints)
            if parts:
                whole.append(check_motion(joints, parts).passed)
            if edited:
                ok = check_motion(joints, edited).passed
                passed.append(ok)
                real_passed.append(check_motion(model.to_joints(item.features[:frames]), edited).passed)
                counts = per_action["+".join(p["action"] for p in edited)]
                counts[0] += ok
                counts[1] += 1
    share = lambda values: float(np.mean(values)) if values else float("nan")  # noqa: E731
    return {
        "rate": share(passed),
        "real_rate": share(real_passed),
        "count": len(passed),
        "unchecked": unchecked,
        "whole_rate": share(whole),
        "whole_count": len(whole),
        "per_action": {k: tuple(v) for k, v in sorted(per_action.items())},
    }


def long_adherence(
    model,
    root: Path,
    items: list[MotionItem],
    cfg: EditingConfig,
    sampling: SamplingConfig,
    seed: int = 0,
    max_items: int | None = None,
) -> dict:
    """Each segment's label parts checked on the long motion of `long_prompts` consecutive items
    (each from its first frame): "rate" over segments with a checkable part, "count", "unchecked"."""
    plans = _labelled(root, items, model, max_items)
    passed, unchecked = [], 0
    k = cfg.long_prompts
    for g in range(0, len(plans) - k + 1, k):
        group = plans[g : g + k]
        out = model.generate_long(
            [item.captions[0].text for item, _, _ in group],
            [frames for _, frames, _ in group],
            sampling,
            seed + g,
            cfg.transition_codes,
            cfg.context_codes,
            check_lengths=False,
        )
        joints = np.asarray(out.joints[0])
        for (_, _, parts), (a, _) in zip(group, out.segments):
            if parts:
                passed.append(check_motion(joints, _shifted(parts, a)).passed)
            else:
                unchecked += 1
    unchecked += len(plans) % k  # the last items that make no full sequence
    return {
        "rate": float(np.mean(passed)) if passed else float("nan"),
        "count": len(passed),
        "unchecked": unchecked,
    }


# -- the tasks ------------------------------------------------------------------------------------
def check_task_model(task: str, model) -> None:
    """ValueError when the model cannot do the task, naming the model and the fix."""
    if task not in TASKS:
        raise ValueError(f"task={task!r} is not a task; choose from {'|'.join(TASKS)}")
    name = model.identity.get("reference") or model.identity.get("checkpoint")
    if task == "upper-body" and not model.part_aware:
        raise ValueError(
            f"task=upper-body needs a part-aware model; {name} is a whole-body model. Pass "
            "text2motion=models:/mmm-upperbody@champion or a part-aware run (make train-stage2-parts)"
        )
    if task != "upper-body" and model.part_aware:
        raise ValueError(
            f"task={task} needs a whole-body model; {name} is part-aware (it edits the upper body only): "
            "pass text2motion=models:/mmm-text2motion@champion or a stage-2 run, or use task=upper-body"
        )


@dataclass
class _Task:
    """What one task needs and what it gathers."""

    model: object
    evaluator: object
    items: list[MotionItem]
    mean: np.ndarray
    std: np.ndarray
    protocol: ProtocolConfig
    cfg: EditingConfig
    root: Path
    split: str
    labels: bool
    max_items: int | None
    head: str
    progress: bool
    prefix: str
    results: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    intervals: dict = field(default_factory=dict)
    series: dict = field(default_factory=lambda: defaultdict(list))
    tables: list = field(default_factory=list)
    artifacts: list = field(default_factory=list)

    def protocol_run(self, produce) -> dict:
        return evaluate_text_to_motion(
            self.model,
            self.evaluator,
            self.items,
            self.mean,
            self.std,
            self.protocol,
            progress=self.progress,
            produce=produce,
            multimodality=False,
        )

    def log_rows(self, proto: dict) -> None:
        """The generated row as edit/<task>/<metric>, the real one as edit/<task>/real_<metric>."""
        for which, tag in (("generated", ""), ("real", "real_")):
            for metric in METRICS:
                value = proto[which].get(metric)
                if value is not None and not math.isnan(value[0]):
                    key = f"{self.prefix}/{tag}{metric}"
                    self.metrics[key], self.intervals[key] = value

    def log(self, values: dict) -> None:
        self.metrics.update({f"{self.prefix}/{k}": v for k, v in values.items() if not math.isnan(v)})


def _fmt(value: float | None, digits: int = 3) -> str:
    return "-" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def evaluate_editing(
    task: str,
    model,
    evaluator,
    items: list[MotionItem],
    mean: np.ndarray,
    std: np.ndarray,
    protocol: ProtocolConfig,
    cfg: EditingConfig,
    root: Path,
    out_dir: Path,
    adherence: bool = True,
    max_items: int | None = None,
    title: str = "",
    split: str = "test",
    progress: bool = True,
) -> dict:
    """Run one editing task on `items` (the split's MotionItems; mean, std (D,) the data's stats);
    returns {"task", "results" (what evaluation.json records), "table" (markdown), "metrics" and
    "intervals" (`edit/<task>/<metric>`), "series" ({metric: [(step, value)]}: the upper-body
    sweep, step = the lower mask in percent), "artifacts" (files written under out_dir)}.
    adherence=False skips the labelled checks; max_items caps their items."""
    cfg.validate()
    if task == "long" and cfg.long_prompts > protocol.batch_size:
        raise ValueError(
            f"editing.long_prompts={cfg.long_prompts}: the captions of one long motion come from one batch, "
            f"so at most protocol.batch_size={protocol.batch_size}"
        )
    check_task_model(task, model)
    head = f"{title}, {protocol.replications} replications" + (
        f" of at most {protocol.max_batches} batches" if protocol.max_batches else ""
    )
    job = _Task(
        model,
        evaluator,
        items,
        mean,
        std,
        protocol,
        cfg,
        root,
        split,
        adherence and (root / "labels").is_dir(),
        max_items,
        head,
        progress,
        f"edit/{task_label(task, cfg)}",
    )
    job.results.update(task=task, editing={**cfg.__dict__, "lower_masks": list(cfg.lower_masks)})
    started = time.perf_counter()
    if task in TEMPORAL_TASKS:
        _temporal(job, task)
    elif task == "long":
        _long(job)
    else:
        _upper_body(job, out_dir)
    job.results["seconds"] = time.perf_counter() - started
    return {
        "task": task,
        "results": job.results,
        "table": "\n\n".join(job.tables),
        "metrics": job.metrics,
        "intervals": job.intervals,
        "series": dict(job.series),
        "artifacts": job.artifacts,
    }


def _text_note(cfg: EditingConfig) -> str:
    return "" if cfg.with_text else ", without text"


def _temporal(job: _Task, task: str) -> None:
    model, cfg, protocol = job.model, job.cfg, job.protocol
    producer = TemporalEdits(model, task, cfg, protocol.sampling)
    proto = job.protocol_run(producer)
    exact = producer.exactness.result()
    job.results.update(generated=proto["generated"], real=proto["real"], exactness=exact)
    job.log_rows(proto)
    job.log(
        {
            f"kept_{stat}_mm_vs_{which}": exact[which][stat]
            for which in ("source", "reconstruction", "reconstruction_far", "tokenizer")
            for stat in ("mean", "max")
        }
    )
    example = ", ".join(f"{a}:{b}" for a, b in keep_ranges(task, 80, cfg))
    row = lambda label, which: (  # noqa: E731
        f"| {label} | {_fmt(exact[which]['mean'], 1)} | {_fmt(exact[which]['max'], 1)} |"
    )
    job.tables += [
        results_table(
            {"Real motion": proto["real"], f"Edited ({task}{_text_note(cfg)})": proto["generated"]},
            f"{task} on {job.head}; kept frames of an 80-frame motion: {example}; MultiModality not "
            "measured for edits",
        ),
        "\n".join(
            [
                f"**Exactness of the kept frames** ({exact['frames']} frames; each frame's pose, mm):",
                "",
                "| edit against | mean | max |",
                "|---|---|---|",
                row("the source's reconstruction (what the method guarantees)", "reconstruction"),
                row(
                    f"the same, kept frames >= {exact['far_frames']} from a generated one "
                    f"({exact['frames_far']} frames)",
                    "reconstruction_far",
                ),
                row("the source", "source"),
                row("(the reconstruction against the source: the tokenizer's own error)", "tokenizer"),
            ]
        ),
    ]
    if job.labels:
        found = temporal_adherence(
            model,
            job.root,
            job.items,
            task,
            cfg,
            protocol.sampling,
            protocol.seed,
            protocol.batch_size,
            job.max_items,
        )
        job.results["adherence"] = found
        job.log({f"adherence_{key}": found[key] for key in ("rate", "real_rate", "whole_rate")})
        job.tables.append(
            f"**Adherence of the generated part**{_text_note(cfg)}: {_fmt(found['rate'])} of "
            f"{found['count']} edits whose "
            f"generated frames cover a labelled action (the same parts on the real motions: "
            f"{_fmt(found['real_rate'])}); {found['unchecked']} edits generated no checkable part; the "
            f"whole edited motion against its label: {_fmt(found['whole_rate'])} of {found['whole_count']}"
        )


def _long(job: _Task) -> None:
    model, cfg, protocol = job.model, job.cfg, job.protocol
    producer = LongSequences(model, cfg, protocol.sampling)
    proto = job.protocol_run(producer)
    smooth = producer.smoothness.result()
    job.results.update(generated=proto["generated"], real=proto["real"], smoothness=smooth)
    job.log_rows(proto)
    job.log(smooth)
    job.tables += [
        results_table(
            {
                "Real motion": proto["real"],
                f"Segments of long motions ({cfg.long_prompts} captions each)": proto["generated"],
            },
            f"long on {job.head}; each segment scored against its caption's real motion; MultiModality "
            "not measured",
        ),
        f"**Transitions**: mean joint acceleration {smooth['transition_acceleration']:.2f} m/s² over "
        f"the transition frames, {smooth['segment_acceleration']:.2f} inside the segments (ratio "
        f"{smooth['transition_ratio']:.2f}; > 1 is a jerk); the segments concatenated without "
        f"transitions: ratio {smooth['cut_ratio']:.2f} at the cuts; "
        f"{smooth['seconds_per_minute']:.1f} s of generation per minute of motion",
    ]
    if job.labels:
        found = long_adherence(
            model, job.root, job.items, cfg, protocol.sampling, protocol.seed, job.max_items
        )
        job.results["adherence"] = found
        job.log({"adherence_rate": found["rate"]})
        job.tables.append(
            f"**Adherence per segment**: {_fmt(found['rate'])} of {found['count']} segments "
            f"({found['unchecked']} without a checkable label)"
        )


def _upper_body(job: _Task, out_dir: Path) -> None:
    model, cfg, protocol = job.model, job.cfg, job.protocol
    sampling = (
        protocol.sampling
        if cfg.upper_body_guidance is None
        else replace(protocol.sampling, guidance_scale=cfg.upper_body_guidance)
    )
    sources = (
        lower_body_sources(job.root, job.split, model.min_frames, model.max_frames) if job.labels else []
    )
    rows, sweep = {}, []
    for mask in sorted({float(cfg.lower_mask), *map(float, cfg.lower_masks)}):
        producer = UpperBodyEdits(model, mask, sampling)
        proto = job.protocol_run(producer)
        rows["Real motion"] = proto["real"]
        main = mask == cfg.lower_mask
        rows[f"Upper-body edit, lower mask {mask:g}" + (" (main)" if main else "")] = proto["generated"]
        entry = {
            "lower_mask": mask,
            "generated": proto["generated"],
            "exactness": producer.exactness.result(),
        }
        if sources:
            entry["adherence"] = upper_body_adherence(
                model, job.root, job.split, cfg.upper_body_sources, mask, protocol.seed, sampling
            )
        sweep.append(entry)
        step = int(round(mask * 100))  # MLflow steps are integers: the mask in percent
        for metric in ("fid", "top1", "diversity"):
            job.series[f"{job.prefix}/sweep/{metric}"].append((step, proto["generated"][metric][0]))
        for key in ("upper", "lower", "both") if sources else ():
            job.series[f"{job.prefix}/sweep/adherence_{key}"].append((step, entry["adherence"][key]))
        if main:
            job.log_rows(proto)
            job.log({f"lower_max_mm_vs_{k}": v["max"] for k, v in entry["exactness"].items()})
            if sources:
                job.log({f"adherence_{k}": entry["adherence"][k] for k in ("upper", "lower", "both")})
    job.results.update(real=rows["Real motion"], sweep=sweep)
    lines = [
        "| lower mask | FID | R-Precision top-1 | Diversity | lower body max mm vs reconstruction / "
        "source | adherence upper | lower | both |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in sweep:
        g, x, a = e["generated"], e["exactness"], e.get("adherence", {})
        lines.append(
            f"| {e['lower_mask']:g} | {g['fid'][0]:.3f} ± {g['fid'][1]:.3f} | {g['top1'][0]:.3f} ± "
            f"{g['top1'][1]:.3f} | {g['diversity'][0]:.3f} ± {g['diversity'][1]:.3f} | "
            f"{_fmt(x['reconstruction']['max'], 2)} / {_fmt(x['source']['max'], 1)} | "
            + " | ".join(_fmt(a.get(k)) for k in ("upper", "lower", "both"))
            + " |"
        )
    if sources:
        done = sweep[0]["adherence"]
        note = f"adherence: {done['edits']} edits of {done['sources']} labelled lower-body clips per mask"
    else:
        note = "adherence: no labelled single lower-body clip in the split" if job.labels else "no labels"
    job.tables += [
        results_table(
            rows,
            f"upper-body on {job.head}; the real motion's lower body kept, the upper body from its "
            f"caption, guidance {sampling.guidance_scale:g}; MultiModality not measured",
        ),
        f"**Lower-body mask ablation** ({note}; plot {PLOT_FILE})\n\n" + "\n".join(lines),
    ]
    out_dir.mkdir(parents=True, exist_ok=True)
    plot = out_dir / PLOT_FILE
    lower_mask_figure(sweep).savefig(plot)
    job.artifacts.append(plot)


def lower_mask_figure(sweep: list[dict]) -> Figure:
    """FID, R-Precision top-1 and Diversity (with intervals) and, when measured, upper-body edit
    adherence (upper, lower, both) against the share of lower-body codes hidden."""
    masks = [e["lower_mask"] for e in sweep]
    labelled = all("adherence" in e for e in sweep) and bool(sweep)
    fig = Figure(figsize=(4.2 * (4 if labelled else 3), 3.4), dpi=110)
    panels = fig.subplots(1, 4 if labelled else 3)
    for ax, (metric, label) in zip(
        panels, (("fid", "FID"), ("top1", "R-Precision top-1"), ("diversity", "Diversity"))
    ):
        ax.errorbar(
            masks,
            [e["generated"][metric][0] for e in sweep],
            yerr=[e["generated"][metric][1] for e in sweep],
            marker="o",
            capsize=3,
        )
        ax.set_xlabel("lower-body codes hidden")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    if labelled:
        ax = panels[3]
        for key in ("upper", "lower", "both"):
            ax.plot(masks, [e["adherence"][key] for e in sweep], marker="o", label=key)
        ax.set_ylim(0, 1.05)
        ax.set_xlabel("lower-body codes hidden")
        ax.set_title("adherence")
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig

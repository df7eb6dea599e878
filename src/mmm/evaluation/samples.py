"""Motions to look at beside the numbers: `mmm evaluate` renders a few captions of the split, each
real motion above what the model made of it, as `samples.gif` (animated, real motions in the top
row) and `samples.png` (a contact sheet, each real motion above the model's) in its output folder
and the run's `samples/`.

The captions are spread evenly over the split. text2motion generates each at its real motion's
length; the temporal edits (inbetween, outpaint, prefix, suffix) keep the task's frames of the real
motion and generate the rest from the caption; upper-body gives the real motion a new upper body
from its caption; long makes one long motion of `editing.long_prompts` captions (with the task's
transition and context codes), under their real motions, each prompt named while it plays.
`mmm ablate` draws the same captions at every setting of a sweep (render_sweep). On labelled data
each generated motion (each segment of a long one, on its own frames) says whether it follows its
caption (the order-aware check of prompt adherence) and, when not, the first condition it fails.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from mmm.data.humanml3d import MotionItem
from mmm.data.synthetic.adherence import check_motion
from mmm.evaluation.adherence import item_parts, ordered_pass
from mmm.evaluation.configs import EditingConfig
from mmm.evaluation.editing import TEMPORAL_TASKS, keep_ranges
from mmm.generation.settings import SamplingConfig
from mmm.render import render_frames, render_gif

log = logging.getLogger(__name__)

RENDERED_TASKS = ("text2motion", *TEMPORAL_TASKS, "upper-body", "long")


def spread(items: list[MotionItem], count: int) -> list[MotionItem]:
    """`count` items evenly spaced over `items`, the first included (all of them when fewer); the
    mirrored copies (ids `M<id>`) only when there are no others, so as not to show a clip twice."""
    originals = [item for item in items if not item.motion_id.startswith("M")] or items
    if count >= len(originals):
        return list(originals)
    return [originals[i * len(originals) // count] for i in range(count)]


def _verdict(joints: np.ndarray, parts: list[dict]) -> str:
    """The order-aware check's verdict: "follows it", or "does not follow it: <the first failed
    condition>"."""
    frames = len(joints)
    if ordered_pass(joints, frames, parts):
        return "follows it"
    clipped = [{**p, "end": min(p["end"], frames)} for p in parts]
    failed = check_motion(joints, clipped).failures
    first = failed[0] if failed else None
    why = (
        f": {first.action} {first.name} {first.value:.2f}, needs {first.op} {first.threshold}"
        if first
        else ""
    )
    return f"does not follow it{why}"


def _made(model, task: str, item: MotionItem, frames: int, editing: EditingConfig, sampling, seed: int):
    """(joints (T, J, 3), what was done) for one item's first caption at `frames` frames."""
    text = item.captions[0].text
    if task == "text2motion":
        return generated(model, [(item, frames)], sampling, seed)[0], "generated"
    source = item.features[:frames]
    if task == "upper-body":
        if editing.upper_body_guidance is not None:  # as the benchmark edits
            sampling = replace(sampling or SamplingConfig(), guidance_scale=editing.upper_body_guidance)
        out = model.edit_upper_body(
            source, text, editing.lower_mask, sampling=sampling, seed=seed, check_lengths=False
        )
        return out.joints[0], f"new upper body, {editing.lower_mask:.0%} of the legs' codes hidden"
    kept = keep_ranges(task, frames, editing, model.unit)
    out = model.edit(source, kept, text if editing.with_text else None, sampling=sampling, seed=seed)
    spans = ", ".join(f"{a}-{b}" for a, b in kept)
    return out.joints[0], f"{task}, frames {spans} kept"


def chosen_items(model, items: list[MotionItem], count: int) -> list[tuple[MotionItem, int]]:
    """(item, frames) for `count` items spread over `items` (see spread), each at its length cut to
    the model's maximum and unit; items shorter than three units are passed over."""
    chosen = []
    for item in spread(items, count):
        frames = min(item.length, model.max_frames) // model.unit * model.unit
        if frames >= 3 * model.unit:
            chosen.append((item, frames))
    return chosen


def generated(model, chosen: list[tuple[MotionItem, int]], sampling=None, seed: int = 0) -> list[np.ndarray]:
    """The model's motion (T, J, 3) for each chosen item's first caption at its length."""
    return [
        model.generate(
            [item.captions[0].text], [frames], sampling, seed=seed + k, check_lengths=False
        ).joints[0]
        for k, (item, frames) in enumerate(chosen)
    ]


def _label(root: Path, item: MotionItem, joints) -> str:
    """The verdict to add to a caption on labelled data (" - follows it", ...), else ""."""
    path = root / "labels" / f"{item.motion_id}.json"
    parts = item_parts(item, json.loads(path.read_text())) if path.exists() else []
    return f" - {_verdict(np.asarray(joints), parts)}" if parts else ""


def _write(motions: list, captions: list[str], columns: int, out_dir: Path, fps: float) -> list[Path]:
    """samples.gif (rows of `columns` panels) and samples.png (six frames a motion) in out_dir."""
    out_dir.mkdir(parents=True, exist_ok=True)
    gif = render_gif(
        motions, out_dir / "samples.gif", captions=captions, fps=fps, size=(240, 240), columns=columns
    )
    # the sheet runs down each column of the GIF: a real motion, then what was made of it
    order = [r * columns + c for c in range(columns) for r in range(len(motions) // columns)]
    sheet = render_frames(
        [motions[i] for i in order],
        out_dir / "samples.png",
        [captions[i] for i in order],
        num_frames=6,
        size=(200, 200),
    )
    return [gif, sheet]


def render_samples(
    model,
    task: str,
    items: list[MotionItem],
    root: Path,
    out_dir: Path,
    count: int,
    editing: EditingConfig,
    sampling=None,
    seed: int = 0,
) -> list[Path]:
    """Write out_dir/samples.gif and samples.png for `count` items (see the module); returns the
    files written ([] when count is 0). task=long renders one long motion whatever the count."""
    if count <= 0 or not items:
        return []
    if task not in RENDERED_TASKS:
        raise ValueError(f"task={task!r}: no samples for it; rendered tasks: {', '.join(RENDERED_TASKS)}")
    if task == "long":
        return _render_long(model, items, root, out_dir, editing, sampling, seed)
    chosen = chosen_items(model, items, count)
    if not chosen:
        return []
    real, made, real_captions, made_captions = [], [], [], []
    for k, (item, frames) in enumerate(chosen):
        joints, what = _made(model, task, item, frames, editing, sampling, seed + k)
        real.append(model.to_joints(item.features[:frames]))
        made.append(joints)
        real_captions.append(f"real {item.name}: {item.captions[0].text}")
        made_captions.append(what + _label(root, item, joints))
    return _write(real + made, real_captions + made_captions, len(real), out_dir, model.fps)


def _render_long(
    model, items: list[MotionItem], root: Path, out_dir: Path, editing: EditingConfig, sampling, seed: int
) -> list[Path]:
    """One long motion of `editing.long_prompts` captions spread over the split: their real motions
    in the top row, the long motion under the first, labelled with the prompt playing."""
    chosen = chosen_items(model, items, editing.long_prompts)
    if len(chosen) < 2:
        log.info("task=long: fewer than 2 captions long enough to render a long motion")
        return []
    texts = [item.captions[0].text for item, _ in chosen]
    out = model.generate_long(
        texts,
        [frames for _, frames in chosen],
        sampling,
        seed,
        editing.transition_codes,
        editing.context_codes,
        check_lengths=False,
    )
    joints = np.asarray(out.joints[0])
    labels = [_label(root, item, joints[a:b]) for (item, _), (a, b) in zip(chosen, out.segments)]
    motions = [model.to_joints(item.features[:frames]) for item, frames in chosen] + [joints]
    captions = [f"real {item.name}: {text}" for (item, _), text in zip(chosen, texts)]
    head = f"long motion of the {len(chosen)} captions above"
    # the GIF's panel is one column wide: there a count, on the sheet's full row each verdict
    followed = sum(label == " - follows it" for label in labels)
    judged = sum(bool(label) for label in labels)
    summary = f"{head}: {followed} of {judged} segments follow theirs" if judged else head
    verdicts = "; ".join(f"{i}{label}" for i, label in enumerate(labels, 1) if label)
    spans = [None] * len(chosen) + [
        [(a, b, f"{i}. {t}") for i, (t, (a, b)) in enumerate(zip(texts, out.segments), 1)]
    ]
    out_dir.mkdir(parents=True, exist_ok=True)
    gif = render_gif(
        motions,
        out_dir / "samples.gif",
        captions=[*captions, summary],
        fps=model.fps,
        size=(240, 240),
        columns=len(chosen),
        spans=spans,
    )
    sheet_captions = [*captions, f"{head}; {verdicts}" if verdicts else head]
    sheet = render_frames(motions, out_dir / "samples.png", sheet_captions, num_frames=6, size=(200, 200))
    return [gif, sheet]


def render_sweep(
    model, chosen: list[tuple[MotionItem, int]], rows: dict[str, list], root: Path, out_dir: Path
) -> list[Path]:
    """An ablation's samples: the chosen items' real motions in the top row, under them each
    setting's motions for the same captions (`rows`: setting -> motions, as `generated` gives them)."""
    if not chosen or not rows:
        return []
    motions = [model.to_joints(item.features[:frames]) for item, frames in chosen]
    captions = [f"real {item.name}: {item.captions[0].text}" for item, _ in chosen]
    for label, made in rows.items():
        motions += made
        captions += [label + _label(root, item, joints) for (item, _), joints in zip(chosen, made)]
    return _write(motions, captions, len(chosen), out_dir, model.fps)

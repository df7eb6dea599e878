"""Prompt adherence: the share of generated motions that satisfy their caption's labels.

For a dataset with `labels/<id>.json` (the synthetic default), every item of a split is generated
from its caption at its length, and the label parts its span covers (shifted into the span) are
checked on the generated joints with the synthetic dataset's adherence checker. No learned
evaluator stands between the text and the figure.

Two figures: strict (each action inside its labelled frame span) and order-aware (the actions
pass in the caption's order on consecutive pieces of the motion, wherever the pieces meet:
`check_in_order`). A caption never says when its second action begins, so for compositions the
order-aware figure is the fair one; for a single action the two differ only where the label
covers part of the clip.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from mmm.data.humanml3d import MotionItem
from mmm.data.synthetic.adherence import check_in_order, check_motion
from mmm.generation.best_of import generate_best_of

# The shortest piece the order-aware check gives an action: the dataset's shortest labelled part
# (2 s at 20 fps), or the clip's share when the clip is shorter than one per action.
_MIN_PART_FRAMES = 40


def parts_in_span(parts: list[dict], start: int, end: int) -> list[dict]:
    """The label parts that the frames [start, end) cover (almost all of), in the span's frame
    indices (clipped to it)."""
    out = []
    for part in parts:
        a, b = max(part["start"], start), min(part["end"], end)
        if b - a >= 0.8 * (part["end"] - part["start"]):  # the span covers (almost all of) this part
            out.append({**part, "start": a - start, "end": b - start})
    return out


def item_parts(item: MotionItem, label: dict) -> list[dict]:
    """The label parts inside the item's span, in the item's frame indices (clipped to it)."""
    return parts_in_span(label["parts"], item.start, item.start + item.length)


def item_groups(parts: list[dict]) -> list[str]:
    """The groups a caption's figures are reported in: "single" (one action) or "composition"
    (several), and also "counts" when an action is to be done more than once ("jumps twice")."""
    groups = ["single" if len(parts) == 1 else "composition"]
    if any(int(p.get("params", {}).get("count", 1)) > 1 for p in parts):
        groups.append("counts")
    return groups


def labelled_captions(
    model, root: str | Path, items: list[MotionItem], max_items: int | None = None
) -> tuple[list[tuple[str, int, list[dict]]], int]:
    """([(caption, frames, label parts)], skipped) of the first `max_items` items: each item's first
    caption at its length (cut to the model's maximum and unit); skipped counts items without a
    label or a covered part."""
    root = Path(root)
    if not (root / "labels").is_dir():
        raise FileNotFoundError(
            f"{root / 'labels'}: no labels; prompt adherence needs a dataset with labels/<id>.json (the "
            "synthetic one)"
        )
    checks, skipped = [], 0
    for item in items[: max_items or len(items)]:
        path = root / "labels" / f"{item.motion_id}.json"
        parts = item_parts(item, json.loads(path.read_text())) if path.exists() else []
        frames = min(item.length, model.max_frames) // model.unit * model.unit
        if not parts or frames < model.unit:
            skipped += 1
            continue
        checks.append((item.captions[0].text, frames, parts))
    return checks, skipped


def ordered_pass(joints, frames: int, parts: list[dict]) -> bool:
    """The order-aware check of one generated motion (T, J, 3) of `frames` frames."""
    joints = np.asarray(joints)
    return check_in_order(joints, parts, min_frames=min(_MIN_PART_FRAMES, frames // len(parts))) is not None


def prompt_adherence(
    model,
    root: str | Path,
    items: list[MotionItem],
    sampling=None,
    seed: int = 0,
    batch_size: int = 32,
    max_items: int | None = None,
    candidates: int = 1,
    judge=None,
    by_clause: bool = True,
    counterfactuals: bool = True,
) -> dict:
    """Prompt adherence of a TextToMotion `model` on `items` (candidates > 1: each motion the best
    of that many draws by `judge`, mmm.generation.best_of.judge_scores: clause by clause unless
    by_clause=False, against count and speed counterfactuals unless counterfactuals=False):

    rate, per_action {actions: (satisfied, total)}: strict; ordered_rate, per_action_ordered: the
    order-aware check; groups {"single" | "composition" | "counts": {"count", "strict", "ordered"}}
    (see item_groups); count:
    items checked; skipped: items without a label or covered part. Actions of a composition are
    joined with "+" in the label's order."""
    checks, skipped = labelled_captions(model, root, items, max_items)
    per_action: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    per_action_ordered: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    groups: dict[str, list[int]] = defaultdict(lambda: [0, 0, 0])  # count, strict, ordered
    satisfied = satisfied_ordered = 0
    for b in range(0, len(checks), batch_size):
        chunk = checks[b : b + batch_size]
        texts, frames = [c[0] for c in chunk], [c[1] for c in chunk]
        if candidates > 1:
            out = generate_best_of(
                model,
                judge,
                texts,
                frames,
                candidates,
                sampling,
                seed=seed + b,
                check_lengths=False,
                by_clause=by_clause,
                counterfactuals=counterfactuals,
            )
        else:
            out = model.generate(texts, frames, sampling, seed=seed + b, check_lengths=False)
        for joints, (_, frames, parts) in zip(out.joints, chunk):
            clipped = [{**p, "end": min(p["end"], frames)} for p in parts]
            joints = np.asarray(joints)
            ok = check_motion(joints, clipped).passed
            in_order = ordered_pass(joints, frames, parts)
            satisfied += ok
            satisfied_ordered += in_order
            key = "+".join(p["action"] for p in parts)
            for table, passed in ((per_action, ok), (per_action_ordered, in_order)):
                table[key][0] += passed
                table[key][1] += 1
            for name in item_groups(parts):
                groups[name][0] += 1
                groups[name][1] += ok
                groups[name][2] += in_order
    share = lambda k, n: k / n if n else float("nan")  # noqa: E731
    return {
        "rate": share(satisfied, len(checks)),
        "ordered_rate": share(satisfied_ordered, len(checks)),
        "count": len(checks),
        "skipped": skipped,
        "per_action": {k: tuple(v) for k, v in sorted(per_action.items())},
        "per_action_ordered": {k: tuple(v) for k, v in sorted(per_action_ordered.items())},
        "groups": {
            name: {"count": n, "strict": share(strict, n), "ordered": share(ordered, n)}
            for name, (n, strict, ordered) in sorted(groups.items())
        },
    }


def adherence_metrics(result: dict, prefix: str = "adherence") -> dict[str, float]:
    """A prompt_adherence result as flat metrics: <prefix>/rate, <prefix>/ordered_rate and
    <prefix>/<group>_{strict,ordered} for each group."""
    metrics = {f"{prefix}/rate": result["rate"], f"{prefix}/ordered_rate": result["ordered_rate"]}
    for group, values in result["groups"].items():
        metrics[f"{prefix}/{group}_strict"] = values["strict"]
        metrics[f"{prefix}/{group}_ordered"] = values["ordered"]
    return metrics

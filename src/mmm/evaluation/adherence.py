"""Prompt adherence: the share of generated motions that satisfy their caption's labels.

For a dataset with `labels/<id>.json` (the synthetic default), every item of a split is generated
from its caption at its length, and the label parts its span covers (shifted into the span) are
checked on the generated joints with the synthetic dataset's adherence checker. No learned
evaluator stands between the text and the figure.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from mmm.data.humanml3d import MotionItem
from mmm.data.synthetic.adherence import check_motion


def item_parts(item: MotionItem, label: dict) -> list[dict]:
    """The label parts inside the item's span, in the item's frame indices (clipped to it)."""
    start, end = item.start, item.start + item.length
    parts = []
    for part in label["parts"]:
        a, b = max(part["start"], start), min(part["end"], end)
        if b - a >= 0.8 * (part["end"] - part["start"]):  # the span covers (almost all of) this part
            parts.append({**part, "start": a - start, "end": b - start})
    return parts


def prompt_adherence(
    model,
    root: str | Path,
    items: list[MotionItem],
    sampling=None,
    seed: int = 0,
    batch_size: int = 32,
    max_items: int | None = None,
) -> dict:
    """{"rate": share satisfied, "count": items checked, "skipped": items without a label or
    covered part, "per_action": {action: (satisfied, total)}} for a TextToMotion `model`."""
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
    per_action: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    satisfied = 0
    for b in range(0, len(checks), batch_size):
        chunk = checks[b : b + batch_size]
        out = model.generate(
            [c[0] for c in chunk], [c[1] for c in chunk], sampling, seed=seed + b, check_lengths=False
        )
        for joints, (_, frames, parts) in zip(out.joints, chunk):
            clipped = [{**p, "end": min(p["end"], frames)} for p in parts]
            ok = check_motion(np.asarray(joints), clipped).passed
            satisfied += ok
            key = "+".join(p["action"] for p in parts)
            per_action[key][0] += ok
            per_action[key][1] += 1
    return {
        "rate": satisfied / len(checks) if checks else float("nan"),
        "count": len(checks),
        "skipped": skipped,
        "per_action": {k: tuple(v) for k, v in sorted(per_action.items())},
    }

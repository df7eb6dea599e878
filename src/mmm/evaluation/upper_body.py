"""Upper-body editing adherence: does an edited motion do the requested upper-body action while
keeping the source's lower-body action?

Sources are the labelled clips of a split whose whole motion is one lower-body action (walk,
squat); each gets a new upper body from every prompt of UPPER_PROMPTS. The synthetic dataset's
checker then tests the requested upper-body action on the whole edited motion and the source's
own label on it too. The source's reconstruction through the tokenizer is checked as well: a
lower-body action the tokenizer already loses cannot be kept by the editor.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from mmm.data.humanml3d import load_motion, read_split
from mmm.data.synthetic.adherence import check_motion

# Upper-body actions of the synthetic vocabulary, phrased as its captions are.
UPPER_PROMPTS = {
    "wave": ({"hand": "both"}, "a person waves both hands"),
    "raise_arms": ({}, "a person raises both arms"),
    "punch": ({"hand": "both"}, "a person punches with both hands"),
}
LOWER_ACTIONS = ("walk", "squat")


def lower_body_sources(
    root: str | Path, split: str, min_frames: int = 40, max_frames: int = 196
) -> list[tuple[str, dict]]:
    """(motion id, its single label part) of the split's clips that are one lower-body action
    over their whole length, sorted by id."""
    root = Path(root)
    if not (root / "labels").is_dir():
        raise FileNotFoundError(
            f"{root / 'labels'}: no labels; upper-body adherence needs a dataset with labels/<id>.json (the "
            "synthetic one)"
        )
    sources = []
    for motion_id in sorted(read_split(root, split)):
        path = root / "labels" / f"{motion_id}.json"
        if not path.exists():
            continue
        label = json.loads(path.read_text())
        if (
            len(label["parts"]) == 1
            and label["parts"][0]["action"] in LOWER_ACTIONS
            and min_frames <= label["num_frames"] <= max_frames
        ):
            sources.append((motion_id, label["parts"][0]))
    return sources


def upper_body_adherence(
    model,
    root: str | Path,
    split: str = "test",
    max_sources: int = 12,
    lower_mask: float = 0.5,
    seed: int = 0,
    sampling=None,
) -> dict:
    """Rates over (source, prompt) edits by a part-aware TextToMotion `model`:
    {"upper": requested upper action satisfied, "lower": source's lower action kept, "both",
     "source_reconstructed": the source's label on its tokenizer reconstruction, "edits",
     "per_action": {"wave on walk": [satisfied both, total], ...}}."""
    root = Path(root)
    sources = lower_body_sources(root, split, model.min_frames, model.max_frames)[:max_sources]
    if not sources:
        raise ValueError(
            f"{root}/{split}.txt: no clip is a single {' or '.join(LOWER_ACTIONS)} action; nothing to edit"
        )
    upper_ok, lower_ok, reconstructed = [], [], []
    per_action: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for i, (motion_id, part) in enumerate(sources):
        features = load_motion(root / "new_joint_vecs" / f"{motion_id}.npy", model.feature_dim)
        frames = features.shape[0] // model.unit * model.unit
        lower_part = [{**part, "start": 0, "end": min(part["end"], frames)}]
        recon = model.to_joints(model.decode([model.encode_motion(features)])[0][:frames])
        reconstructed.append(check_motion(recon, lower_part).passed)
        for j, (action, (params, text)) in enumerate(UPPER_PROMPTS.items()):
            out = model.edit_upper_body(
                features, text, lower_mask=lower_mask, sampling=sampling, seed=seed + 7 * i + j
            )
            joints = np.asarray(out.joints[0])
            up = check_motion(
                joints, [{"action": action, "params": params, "start": 0, "end": len(joints)}]
            ).passed
            low = check_motion(joints, lower_part).passed
            upper_ok.append(up)
            lower_ok.append(low)
            key = f"{action} on {part['action']}"
            per_action[key][0] += up and low
            per_action[key][1] += 1
    both = [u and low for u, low in zip(upper_ok, lower_ok)]
    return {
        "upper": float(np.mean(upper_ok)),
        "lower": float(np.mean(lower_ok)),
        "both": float(np.mean(both)),
        "source_reconstructed": float(np.mean(reconstructed)),
        "edits": len(both),
        "sources": len(sources),
        "per_action": dict(per_action),
    }

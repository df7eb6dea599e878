"""Why a text-to-motion model fails the prompts it fails, on labelled (synthetic) data.

    python benchmarks/adherence_diagnosis.py [--model models:/mmm-text2motion@champion]
        [--data data/synthetic] [--split test] [--out outputs/bench/adherence_diagnosis.json]

Prints and writes (JSON):
- failures: per action (compositions together) the checker's failed conditions, counted;
- phrasing: order-aware adherence of captions that occur word for word among the training
  captions against new phrasings, for single actions and compositions;
- text_probe: whether the caption's sentence embedding tells a jump's or squat's count and a
  walk's speed (a linear probe fitted on the training captions, and nearest neighbour by cosine);
- walk_codes: how much the code histograms of slow, normal and fast training walks overlap;
- round_trip: order-aware adherence of the test motions after the tokenizer's encode and decode,
  per action, compositions and counts: the ceiling a transformer over these codes can reach.
- locomotion_speeds: the mean speed (m/s) and the share passing the checker of the split's single
  runs and walks (per speed word): the data, after the nearest codes' round trip (what stage 2
  learns from), and generated at their true lengths under a few sampling settings (sampler seeds
  0 and 1): whether the codes or the transformer lose a gait's speed.
The README's "What the `make demo` model follows, and why not the rest" quotes these figures;
tests/test_adherence_diagnosis.py checks the counting with an oracle model (each caption's own motion).
"""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from mmm.cli.common import DEFAULT_TRACKING_URI
from mmm.data.configs import DataConfig
from mmm.data.synthetic.adherence import FPS, check_in_order, check_motion, mean_speed
from mmm.evaluation.adherence import item_parts
from mmm.generation.model import TextToMotion
from mmm.generation.settings import SamplingConfig
from mmm.tracking import resolve_tracking_uri

MIN_PART_FRAMES = 40  # as prompt_adherence's order-aware check


def labelled_items(root: Path, split: str, model, features: bool = False) -> list[tuple]:
    """(first caption, frames, label parts in the item's frames[, the item's features (frames, D)])
    of the split's labelled items."""
    items, _ = DataConfig(root=str(root)).items(split, root)
    out = []
    for item in items:
        path = root / "labels" / f"{item.motion_id}.json"
        parts = item_parts(item, json.loads(path.read_text())) if path.exists() else []
        frames = min(item.length, model.max_frames) // model.unit * model.unit
        if parts and frames >= model.unit:
            row = (item.captions[0].text, frames, [{**p, "end": min(p["end"], frames)} for p in parts])
            out.append(row + ((item.features[:frames],) if features else ()))
    return out


def in_order(joints: np.ndarray, parts: list[dict], frames: int) -> bool:
    return check_in_order(joints, parts, min_frames=min(MIN_PART_FRAMES, frames // len(parts))) is not None


def generated_checks(model, checks, seed: int = 0, batch: int = 32):
    """Per item: (caption, parts, strict result, passes in order)."""
    rows = []
    for b in range(0, len(checks), batch):
        chunk = checks[b : b + batch]
        out = model.generate([c[0] for c in chunk], [c[1] for c in chunk], seed=seed + b, check_lengths=False)
        for joints, (text, frames, parts) in zip(out.joints, chunk):
            joints = np.asarray(joints)
            rows.append((text, parts, check_motion(joints, parts), in_order(joints, parts, frames)))
    return rows


def round_trip(model, items) -> dict:
    """Order-aware adherence of each item's motion after the tokenizer's encode and decode."""
    counts: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for b in range(0, len(items), 64):
        chunk = items[b : b + 64]
        decoded = model.decode(model.encode_motions([row[3] for row in chunk]))
        for features, (_, frames, parts, _) in zip(decoded, chunk):
            passed = in_order(model.to_joints(features), parts, frames)
            groups = ["all", parts[0]["action"] if len(parts) == 1 else "composition"]
            groups += ["single"] * (len(parts) == 1)
            groups += ["counts"] * any(int(p.get("params", {}).get("count", 1)) > 1 for p in parts)
            for g in groups:
                counts[g][0] += passed
                counts[g][1] += 1
    return {k: {"followed": a, "of": n, "rate": a / n} for k, (a, n) in sorted(counts.items())}


def failures(rows) -> dict:
    table: dict[str, Counter] = defaultdict(Counter)
    totals: Counter = Counter()
    for _, parts, result, _ in rows:
        key = parts[0]["action"] if len(parts) == 1 else "composition"
        totals[key] += 1
        for c in result.failures:
            table[key][f"{c.action}: {c.name}"] += 1
    return {k: {"captions": totals[k], "failed": dict(table[k].most_common())} for k in sorted(totals)}


def phrasing(rows, training_captions: set[str]) -> dict:
    groups: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for text, parts, _, ordered in rows:
        key = f"{'single' if len(parts) == 1 else 'composition'}, " + (
            "caption seen in training" if text in training_captions else "new phrasing"
        )
        groups[key][0] += ordered
        groups[key][1] += 1
    return {k: {"followed": a, "of": n, "rate": a / n} for k, (a, n) in sorted(groups.items())}


def attribute(parts: list[dict]) -> tuple[str, object] | None:
    if len(parts) != 1:
        return None
    action, params = parts[0]["action"], parts[0].get("params", {})
    if action in ("jump", "squat"):
        return "count", params["count"]
    if action == "walk":
        return "speed", params["speed"]
    return None


def text_probe(model, train, test, steps: int = 500) -> dict:
    """Linear probe and nearest neighbour on the sentence embedding, per attribute."""
    out = {}
    for name in ("count", "speed"):
        a = [(t, y[1]) for t, _, parts in train if (y := attribute(parts)) and y[0] == name]
        b = [(t, y[1]) for t, _, parts in test if (y := attribute(parts)) and y[0] == name]
        if not a or not b:
            continue
        classes = sorted({y for _, y in a}, key=str)
        xa = model.encode_text([t for t, _ in a]).sentence.float().cpu()
        xb = model.encode_text([t for t, _ in b]).sentence.float().cpu()
        ya = torch.tensor([classes.index(y) for _, y in a])
        yb = torch.tensor([classes.index(y) if y in classes else -1 for _, y in b])
        torch.manual_seed(0)
        probe = torch.nn.Linear(xa.shape[1], len(classes))
        opt = torch.optim.Adam(probe.parameters(), lr=1e-2, weight_decay=1e-4)
        for _ in range(steps):
            opt.zero_grad()
            torch.nn.functional.cross_entropy(probe(xa), ya).backward()
            opt.step()
        with torch.no_grad():
            linear = (probe(xb).argmax(1) == yb).float().mean().item()
        na, nb = torch.nn.functional.normalize(xa, dim=1), torch.nn.functional.normalize(xb, dim=1)
        nearest = (ya[(nb @ na.T).argmax(1)] == yb).float().mean().item()
        out[name] = {
            "classes": [str(c) for c in classes],
            "train_captions": len(a),
            "test_captions": len(b),
            "linear_probe_accuracy": linear,
            "nearest_neighbour_accuracy": nearest,
        }
    return out


def walk_codes(model, root: Path) -> dict:
    """Overlap (sum of the minimum of the normalized histograms) of the codes of whole-clip training
    walks of each pair of speeds."""
    items, _ = DataConfig(root=str(root)).clips("train", root)
    hist: dict[str, Counter] = defaultdict(Counter)
    for motion_id, features in items.items():
        path = root / "labels" / f"{motion_id}.json"
        if not path.exists():
            continue
        parts = json.loads(path.read_text())["parts"]
        if len(parts) == 1 and parts[0]["action"] == "walk":
            codes = model.encode_motion(features[: model.max_frames])
            hist[parts[0]["params"]["speed"]].update(np.asarray(codes).reshape(-1).tolist())
    out = {}
    speeds = sorted(hist)
    for i, a in enumerate(speeds):
        for b in speeds[i + 1 :]:
            ha, hb = hist[a], hist[b]
            na, nb = sum(ha.values()), sum(hb.values())
            out[f"{a}/{b}"] = sum(min(ha[c] / na, hb[c] / nb) for c in set(ha) | set(hb))
    return out


SPEED_SAMPLING = {  # what locomotion_speeds generates under
    "guidance 1": SamplingConfig(),
    "guidance 1.5": SamplingConfig(guidance_scale=1.5),
    "guidance 3": SamplingConfig(guidance_scale=3.0),
    "guidance 1.5, temperature 0.5": SamplingConfig(guidance_scale=1.5, temperature=0.5),
}


def locomotion_speeds(model, items, seeds: tuple[int, ...] = (0, 1)) -> dict:
    """Per gait ("run", "walk-slow", ...): {source: {"speed", "passed", "of", "draws_per_item"}}
    for the data, its nearest-code round trip and each SPEED_SAMPLING setting; items carry their
    features."""
    items = [r for r in items if len(r[2]) == 1 and r[2][0]["action"] in ("run", "walk")]
    gaits = [
        parts[0]["action"] + (f"-{parts[0]['params']['speed']}" if parts[0]["action"] == "walk" else "")
        for _, _, parts, _ in items
    ]
    joints: dict[str, list] = {"data": [model.to_joints(r[3]) for r in items]}
    search = model.tokenizer.encode_cfg
    # The codes stage 2 learns from (token_encoding: nearest); the model caches codes per encoding.
    model.tokenizer.encode_cfg = replace(search, candidates=1)
    try:
        joints["nearest-code round trip"] = [
            model.to_joints(f) for f in model.decode(model.encode_motions([r[3] for r in items]))
        ]
    finally:
        model.tokenizer.encode_cfg = search
    for name, sampling in SPEED_SAMPLING.items():
        joints[name] = []
        for seed in seeds:
            texts, frames = [r[0] for r in items], [r[1] for r in items]
            out = model.generate(texts, frames, sampling=sampling, seed=seed, check_lengths=False)
            joints[name] += [np.asarray(j) for j in out.joints]
    report: dict[str, dict] = defaultdict(dict)
    for source, motions in joints.items():
        repeats = len(motions) // len(items)
        for gait in sorted(set(gaits)):
            rows = [
                (mean_speed(np.asarray(m), FPS), check_motion(m, items[i % len(items)][2]).passed)
                for i, m in enumerate(motions)
                if gaits[i % len(items)] == gait
            ]
            report[gait][source] = {
                "speed": float(np.mean([v for v, _ in rows])),
                "passed": int(sum(ok for _, ok in rows)),
                "of": len(rows),
                "draws_per_item": repeats,
            }
    return dict(report)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="models:/mmm-text2motion@champion")
    parser.add_argument("--data", default="data/synthetic")
    parser.add_argument("--split", default="test")
    parser.add_argument("--tracking-uri", default=DEFAULT_TRACKING_URI)
    parser.add_argument("--out", default="outputs/bench/adherence_diagnosis.json")
    args = parser.parse_args()
    root = Path(args.data)
    if not (root / "labels").is_dir():
        raise SystemExit(
            f"{root / 'labels'}: no labels; the diagnosis needs labelled data (the synthetic set)"
        )
    model = TextToMotion.load(args.model, resolve_tracking_uri(args.tracking_uri))
    with_features = labelled_items(root, args.split, model, features=True)
    test = [row[:3] for row in with_features]  # the same rows without the features
    train = labelled_items(root, "train", model)
    training_captions = {
        c.text for item in DataConfig(root=str(root)).items("train", root)[0] for c in item.captions
    }
    rows = generated_checks(model, test)
    report = {
        "model": args.model,
        "data": str(root),
        "split": args.split,
        "captions": len(rows),
        "failures": failures(rows),
        "phrasing": phrasing(rows, training_captions),
        "text_probe": text_probe(model, train, test),
        "walk_codes": walk_codes(model, root),
        "round_trip": round_trip(model, with_features),
        "locomotion_speeds": locomotion_speeds(model, with_features),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(report, indent=2))
    tmp.replace(out)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()

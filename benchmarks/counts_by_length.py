"""Are counts followed at any length? (README, "Generating and editing": counts and the length).

Every single-action caption of a labelled split whose action has a count ("jumps twice", "squats
three times") is drawn at its true length scaled by each of `--scales` (rounded to the model's unit
of frames, within its maximum), `--draws` times with different seeds, and checked against its
label over the whole motion. Printed per action and count, for each scale: the share of draws
doing the asked number, and how many did fewer or more.

    python benchmarks/counts_by_length.py --data data/synthetic [--model REF] [--scales 0.75 1 1.25 1.5]
"""

from __future__ import annotations

import argparse
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from mmm.data.configs import DataConfig
from mmm.data.synthetic.adherence import check_motion
from mmm.evaluation.adherence import labelled_captions
from mmm.generation.model import TextToMotion


def counted(joints, frames: int, part: dict) -> tuple[bool, float]:
    """(followed, the number the checker counted) of one single-action motion."""
    count = int(part["params"]["count"])
    result = check_motion(joints, [{**part, "start": 0, "end": frames}])
    done = next(c.value for c in result.conditions if c.op == "==" and c.threshold == count)
    return result.passed, done


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a labelled dataset folder (labels/<id>.json)")
    p.add_argument("--split", default="test")
    p.add_argument("--model", default=None, help="stage-2 reference (default: the champion)")
    p.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    p.add_argument("--scales", type=float, nargs="+", default=[0.75, 1.0, 1.25, 1.5])
    p.add_argument("--draws", type=int, default=2, help="seeds per caption and scale")
    p.add_argument("--batch", type=int, default=64)
    args = p.parse_args()
    if any(s <= 0 for s in args.scales) or args.draws < 1:
        p.error(f"--scales must be positive and --draws at least 1 (got {args.scales}, {args.draws})")
    root = Path(args.data)
    model = TextToMotion.load(args.model, args.tracking_uri)
    items, _ = DataConfig(root=str(root)).items(args.split, root)
    checks, skipped = labelled_captions(model, root, items)
    counts = [(text, frames, parts[0]) for text, frames, parts in checks if len(parts) == 1]
    counts = [c for c in counts if "count" in c[2].get("params", {})]
    print(
        f"{len(counts)} single-action captions with a count in {root} {args.split} (of {len(checks)} "
        f"labelled; {skipped} without a checkable label); {args.draws} draws per scale"
    )
    unit, longest = model.unit, model.max_frames
    # (action, count) -> scale -> [followed, fewer, more]
    tally: dict[tuple[str, int], dict[float, np.ndarray]] = defaultdict(
        lambda: defaultdict(lambda: np.zeros(3))
    )
    for scale in args.scales:
        for draw in range(args.draws):
            for b in range(0, len(counts), args.batch):
                chunk = counts[b : b + args.batch]
                frames = [min(longest, max(2 * unit, round(f * scale / unit) * unit)) for _, f, _ in chunk]
                out = model.generate(
                    [c[0] for c in chunk], frames, None, seed=1000 * draw + b, check_lengths=False
                )
                for joints, n, (_, _, part) in zip(out.joints, frames, chunk):
                    followed, done = counted(np.asarray(joints), n, part)
                    asked = int(part["params"]["count"])
                    tally[(part["action"], asked)][scale] += [followed, done < asked, done > asked]
    print(
        "| action | count | captions | "
        + " | ".join(f"x{s:g} followed (fewer / more)" for s in args.scales)
        + " |"
    )
    print("|---|---|---|" + "---|" * len(args.scales))
    captions = Counter((part["action"], int(part["params"]["count"])) for _, _, part in counts)
    for (action, asked), by_scale in sorted(tally.items()):
        n = captions[(action, asked)]
        cells = []
        for s in args.scales:
            followed, fewer, more = by_scale[s]
            cells.append(f"{followed / (n * args.draws):.2f} ({int(fewer)} / {int(more)})")
        print(f"| {action} | {asked} | {n} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()

"""How much best of N can gain, and how much of it the judge takes (README, "Best of N").

Every caption of a labelled split is drawn N times at its true length (one batch per chunk, as
`mmm.generation.best_of` draws them); each draw is checked order-aware. Printed per group, on the
same draws: one draw (the mean over the N: what `mmm evaluate` measures with one candidate, with
less of one seed's noise), the judge's pick (what it measures with N), and the share where any of
the N passes (what a perfect judge would reach).

    python benchmarks/best_of_headroom.py --data data/synthetic-large --candidates 4 [--guidance 1.5]
        [--model REF] [--judge REF] [--seed 0] [--max-items N] [--whole-caption] [--no-counterfactuals]
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from mmm.data.configs import DataConfig
from mmm.evaluation.adherence import item_groups, labelled_captions, ordered_pass
from mmm.evaluation.evaluators import load_judge
from mmm.generation.best_of import check_candidates, check_judge, judge_scores
from mmm.generation.model import TextToMotion
from mmm.generation.sampler import SamplingConfig


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a labelled dataset folder (labels/<id>.json)")
    p.add_argument("--split", default="test")
    p.add_argument("--candidates", type=int, default=4)
    p.add_argument("--model", default=None, help="stage-2 reference (default: the champion)")
    p.add_argument("--judge", default=None, help="evaluator reference (default: its champion)")
    p.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    p.add_argument("--guidance", type=float, default=1.0, help="classifier-free guidance of every draw")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--whole-caption", action="store_true", help="judge the whole caption only, not clause by clause"
    )
    p.add_argument(
        "--no-counterfactuals",
        action="store_true",
        help="do not judge captions with a count or speed word against their counterfactuals",
    )
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--max-items", type=int, default=None)
    args = p.parse_args()
    n = check_candidates(args.candidates, "--candidates")
    sampling = SamplingConfig(guidance_scale=args.guidance)  # checks the scale
    root = Path(args.data)
    model = TextToMotion.load(args.model, args.tracking_uri)
    judge = load_judge(args.judge, args.tracking_uri)
    check_judge(model, judge)
    items, _ = DataConfig(root=str(root)).items(args.split, root)
    checks, skipped = labelled_captions(model, root, items, args.max_items)
    print(f"{len(checks)} captions of {root} {args.split} ({skipped} without a checkable label)")
    started = time.perf_counter()
    tally: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(4))  # captions, one draw, judge, any
    for b in range(0, len(checks), args.batch):
        chunk = checks[b : b + args.batch]
        texts, frames = [c[0] for c in chunk], [c[1] for c in chunk]
        out = model.generate(texts * n, frames * n, sampling, seed=args.seed + b, check_lengths=False)
        scores = judge_scores(
            judge, texts * n, out.features, not args.whole_caption, not args.no_counterfactuals
        ).reshape(n, len(chunk))
        passed = np.array(
            [ordered_pass(joints, f, parts) for joints, (_, f, parts) in zip(out.joints, chunk * n)]
        ).reshape(n, len(chunk))
        picked = passed[scores.argmax(0), np.arange(len(chunk))]
        for i, (_, _, parts) in enumerate(chunk):
            for group in ["all", *item_groups(parts)]:
                tally[group] += [1, passed[:, i].mean(), picked[i], passed[:, i].any()]
    print(f"best of {n}, guidance {args.guidance:g}, seed {args.seed}: {time.perf_counter() - started:.0f} s")
    print("| group | captions | one draw | the judge's pick | any of the draws |")
    print("|---|---|---|---|---|")
    for group, (count, one, picked, any_) in tally.items():
        print(f"| {group} | {int(count)} | {one / count:.3f} | {picked / count:.3f} | {any_ / count:.3f} |")


if __name__ == "__main__":
    main()

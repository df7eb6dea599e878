"""Does the evaluator read counts and speeds? (README, "Best of N").

For every caption of a split that has counterfactuals (mmm.evaluation.counterfactuals: the count
or a speed word changed), the evaluator scores the real motion against its own caption and against
each counterfactual. Printed: the share of captions whose own wording scores above all of its
counterfactuals (chance is 1 / (1 + the number of counterfactuals)), for counts and for speeds.

    python benchmarks/judge_counterfactuals.py --data data/synthetic-large [--judge REF] [--split test]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from mmm.data.configs import DataConfig
from mmm.evaluation.counterfactuals import counterfactual_ranking
from mmm.evaluation.evaluators import load_judge


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="a dataset folder")
    p.add_argument("--split", default="test")
    p.add_argument("--judge", default=None, help="evaluator reference (default: its champion)")
    p.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    args = p.parse_args()
    judge = load_judge(args.judge, args.tracking_uri)
    items, _ = DataConfig(root=args.data).items(args.split, args.data)
    with torch.no_grad():
        result = counterfactual_ranking(judge, items)
    print(f"{args.data} {args.split}: {len(items)} motions; judge {args.judge or 'the evaluator champion'}")
    print("| change | captions | own caption ranked first | chance |")
    print("|---|---|---|---|")
    for kind, row in result.items():
        print(f"| {kind} | {row['captions']} | {row['first']:.3f} | {row['chance']:.3f} |")


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()

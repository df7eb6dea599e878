"""Plot the prompt-adherence learning curves (`val_adherence/*`, logged by the AdherenceCurve
callback at each validation) of stage-2 runs, one panel per run, side by side.

    python benchmarks/adherence_curves.py RUN_ID[=LABEL] [RUN_ID[=LABEL] ...] --out docs/curves.png
        [--tracking-uri sqlite:///mlflow.db] [--metric ordered]

A run without such metrics (trained on unlabelled data, or with callbacks.adherence_captions=0) is
an error that names it. The README's curves were drawn with this script.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from mlflow.exceptions import MlflowException  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from mmm.atomic import atomic_write  # noqa: E402
from mmm.cli.common import DEFAULT_TRACKING_URI  # noqa: E402
from mmm.tracking import resolve_tracking_uri  # noqa: E402


def curve_names(run, metric: str) -> dict[str, str]:
    """{label: metric key} of the run's order-aware or strict figures: overall ("all"), then each
    group the run logged (`val_adherence/<group>_<metric>`, as adherence_metrics names them)."""
    names = {"all": "val_adherence/ordered_rate" if metric == "ordered" else "val_adherence/rate"}
    suffix = f"_{metric}"
    for key in sorted(run.data.metrics):
        if key.startswith("val_adherence/") and key.endswith(suffix):
            names[key.removeprefix("val_adherence/").removesuffix(suffix)] = key
    return names


def run_curves(client: MlflowClient, run_id: str, metric: str) -> dict[str, list[tuple[int, float]]]:
    """{group label: [(step, value), ...]} of one run."""
    try:
        run = client.get_run(run_id)
    except MlflowException as err:
        raise SystemExit(f"run {run_id}: not in this tracking store ({err.message}); pass --tracking-uri")
    curves = {}
    for label, key in curve_names(run, metric).items():
        history = sorted((m.step, m.value) for m in client.get_metric_history(run_id, key))
        if history:
            curves[label] = history
    if not curves:
        known = sorted(k for k in run.data.metrics if k.startswith("val_adherence/"))
        raise SystemExit(
            f"run {run_id} ({run.info.run_name}) has no {metric} val_adherence/* curves "
            f"(has: {known or 'none'}); "
            "train stage 2 on labelled data with callbacks.adherence_captions > 0"
        )
    return curves


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="RUN_ID or RUN_ID=LABEL (the panel's title)")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--tracking-uri", default=DEFAULT_TRACKING_URI)
    parser.add_argument("--metric", choices=("ordered", "strict"), default="ordered")
    args = parser.parse_args(argv)

    client = MlflowClient(tracking_uri=resolve_tracking_uri(args.tracking_uri))
    panels = []
    for spec in args.runs:
        run_id, _, label = spec.partition("=")
        panels.append((label or run_id[:8], run_curves(client, run_id, args.metric)))

    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 3.6), sharey=True, squeeze=False)
    for ax, (title, curves) in zip(axes[0], panels):
        for label, points in curves.items():
            steps, values = zip(*points)
            ax.plot(
                steps, values, marker="o", markersize=3, label=label, linewidth=2 if label == "all" else 1
            )
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("training step")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f"validation captions followed ({args.metric})")
    axes[0][-1].legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(args.out, "wb") as fh:
        fig.savefig(fh, dpi=110, format="png")
    plt.close(fig)
    print(f"wrote {args.out}: {', '.join(title for title, _ in panels)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The supplementary's ablation tables as runnable sweeps (`mmm ablate KIND [key=value ...]`).

    reset         Table 8   codebook reset every N steps            (trains stage 1 and stage 2 per value)
    cross-layers  Table 9   cross-attention layers of the total      (trains stage 2 per value)
    schedule      Table 10  mask schedule x iterations               (inference only)
    temperature   Table 11  sampling temperature                     (inference only)
    topk          Table 12  top-k as a fraction of the codebook      (inference only)
    topp          Table 13  top-p                                    (inference only)

Each sweep is a parent MLflow run (experiment `mmm-ablations`) with one nested run per setting
holding the protocol's figures; training runs of a setting go to their stage's experiment, tagged
with the parent. The table (markdown and CSV, the paper's columns) and a plot are written to
`<output_dir>/<kind>/` and logged to the parent run, with `samples` captions of the split drawn at
every setting under their real motions (samples.gif/png, the parent's `samples/`). The grids in
conf/ablate.yaml are reduced for a CPU; the paper's grids are in the comments there.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import asdict
from pathlib import Path

import mlflow
from matplotlib.figure import Figure
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig

from mmm.config import to_object
from mmm.data.humanml3d import load_stats
from mmm.device import check_device
from mmm.evaluation.configs import (
    ABLATIONS,
    AblationConfig,
    ProtocolConfig,
    check_samples,
    check_sweep,
    sweep_settings,
    sweep_stage1_overrides,
    sweep_stage2_overrides,
)
from mmm.evaluation.evaluators import load_evaluator
from mmm.evaluation.protocol import METRICS, evaluate_text_to_motion, results_table
from mmm.evaluation.samples import chosen_items, generated, render_sweep
from mmm.generation.model import TextToMotion
from mmm.generation.settings import SamplingConfig
from mmm.tracking import artifact_location, prepare_experiment, resolve_tracking_uri
from mmm.training.configs import load_stage1_config, load_stage2_config
from mmm.training.stage1 import train_stage1
from mmm.training.stage2 import train_stage2

log = logging.getLogger(__name__)


def _train_models(change: dict, cfg: AblationConfig, parent_run_id: str):
    """Train what a training sweep's setting changes; returns the stage-2 checkpoint."""
    run_name = f"ablation-{parent_run_id[:8]}"
    stage1 = cfg.stage1
    overrides = sweep_stage1_overrides(cfg, change, run_name)
    if overrides is not None:
        stage1 = train_stage1(load_stage1_config(overrides)).best_checkpoint
    result = train_stage2(load_stage2_config(sweep_stage2_overrides(cfg, change, run_name, stage1)))
    return result.best_checkpoint


def run_ablation(kind: str, cfg_node: DictConfig) -> dict:
    """Run a sweep; returns {"rows": {label: results}, "table": markdown, "files": [...]}."""
    cfg: AblationConfig = to_object(cfg_node)
    check_device(cfg.device)
    table_no, title = ABLATIONS[kind] if kind in ABLATIONS else (None, None)
    rows_spec = sweep_settings(kind, cfg.grids)
    check_sweep(kind, rows_spec, cfg)
    check_samples(cfg.samples)
    tracking_uri = resolve_tracking_uri(cfg.logger.tracking_uri)
    mlflow.set_tracking_uri(tracking_uri)

    # Created when missing; another process creating it at the same time is not an error.
    experiment_id = prepare_experiment(
        MlflowClient(tracking_uri), "mmm-ablations", artifact_location(tracking_uri, cfg.logger.artifact_root)
    )
    items, _ = cfg.data.items(cfg.split, cfg.data.root)
    mean, std = load_stats(cfg.data.root, cfg.data.feature_dim)
    evaluator = load_evaluator(cfg.evaluator, tracking_uri, device=cfg.device)
    out_dir = Path(cfg.output_dir) / kind
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict] = {}
    with mlflow.start_run(experiment_id=experiment_id, run_name=f"ablation-{kind}") as parent:
        mlflow.set_tags({"mmm.ablation": kind, "paper.table": str(table_no), "evaluator": evaluator.identity})
        mlflow.log_params(
            {
                "kind": kind,
                "settings": json.dumps([label for label, _ in rows_spec])[:500],
                "replications": cfg.protocol.replications,
            }
        )
        shared_model = None
        # the rendered captions, each setting's motions of them, and a model to draw them with
        chosen, sample_rows, drawer = None, {}, None
        for label, change in rows_spec:
            with mlflow.start_run(experiment_id=experiment_id, run_name=label, nested=True):
                if "sampling" in change:
                    shared_model = shared_model or TextToMotion.load(
                        cfg.text2motion, tracking_uri, device=cfg.device
                    )
                    model = shared_model
                    sampling = SamplingConfig(**{**asdict(cfg.protocol.sampling), **change["sampling"]})
                else:
                    checkpoint = _train_models(change, cfg, parent.info.run_id)
                    model = TextToMotion.load(checkpoint, tracking_uri, device=cfg.device)
                    sampling = cfg.protocol.sampling
                protocol = ProtocolConfig(**{**asdict(cfg.protocol), "sampling": sampling})
                result = evaluate_text_to_motion(model, evaluator, items, mean, std, protocol)
                rows[label] = result["generated"]
                chosen = chosen if chosen is not None else chosen_items(model, items, cfg.samples)
                sample_rows[label] = generated(model, chosen, sampling, cfg.protocol.seed)
                drawer = model
                mlflow.log_params(
                    {
                        "setting": label,
                        **{f"change.{k}": str(v)[:200] for k, v in change.items()},
                        "model": model.identity.get("reference"),
                    }
                )
                mlflow.log_metrics({m: v[0] for m, v in result["generated"].items() if not math.isnan(v[0])})
                mlflow.log_metrics(
                    {f"{m}_ci": v[1] for m, v in result["generated"].items() if not math.isnan(v[0])}
                )
        table = results_table(rows, f"Table {table_no} ({title}), {cfg.protocol.replications} replications")
        files = write_outputs(rows, table, out_dir, title)
        for path in files:
            mlflow.log_artifact(str(path))
        samples = render_sweep(drawer, chosen or [], sample_rows, Path(cfg.data.root), out_dir)
        for path in samples:
            mlflow.log_artifact(str(path), "samples")
        files += samples
    return {"rows": rows, "table": table, "files": [str(p) for p in files]}


def write_outputs(rows: dict[str, dict], table: str, out_dir: Path, title: str) -> list[Path]:
    md = out_dir / "table.md"
    md.write_text(table + "\n")
    path = out_dir / "table.csv"
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["setting", *[f"{m}{suffix}" for m in METRICS for suffix in ("", "_ci")]])
        for label, row in rows.items():
            writer.writerow(
                [label, *[f"{row[m][i]:.5f}" if m in row else "" for m in METRICS for i in (0, 1)]]
            )
    return [md, path, plot_rows(rows, out_dir / "plot.png", title)]


def plot_rows(rows: dict[str, dict], path: Path, title: str) -> Path:
    labels = list(rows)
    shown = [
        ("top1", "R-Precision top-1"),
        ("fid", "FID"),
        ("matching_score", "MM-Dist"),
        ("multimodality", "MultiModality"),
    ]
    fig = Figure(figsize=(3.2 * len(shown), 3.2), dpi=110)
    axes = fig.subplots(1, len(shown))
    for ax, (metric, name) in zip(axes, shown):
        means = [rows[lb][metric][0] for lb in labels]
        errs = [rows[lb][metric][1] for lb in labels]
        ax.errorbar(range(len(labels)), means, yerr=errs, marker="o", capsize=3)
        ax.set_xticks(range(len(labels)), labels, rotation=60, ha="right", fontsize=7)
        ax.set_title(name, fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    return path

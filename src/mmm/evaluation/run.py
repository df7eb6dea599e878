"""`mmm evaluate [key=value ...]`: the protocol for a text-to-motion model, reconstruction metrics
for its tokenizer, and prompt adherence on a labelled dataset; logged to MLflow and printed.

One MLflow run per evaluation (experiment mmm-evaluation), named `evaluate-<data>-<time>` unless
`logger.run_name` is set, open while the evaluation works (its duration is the evaluation's; FAILED
when it raises). Metrics: `generated/<metric>` and `real/<metric>` (the mean over replications),
`recon/fid`, `recon/mpjpe_root_aligned_mm`, `recon/mpjpe_global_mm`, `recon/adherence_rate` (labelled
clips whose actions survive the tokenizer's round trip), `adherence/rate` (strict),
`adherence/ordered_rate` and per group `adherence/{single,composition,counts}_{strict,ordered}`
(`adherence_best<N>/...` with adherence_candidates=N: each motion the best of N by the judge); the
intervals (1.96·std/sqrt(n)) are in the table and evaluation.json, not charted. The run's
description holds the table with links to the model's run and registered version; artifacts
`evaluation.md` (the table) and `evaluation.json`; tags: the model's and evaluator's identities,
the data fingerprint (also the run's dataset input) and the git commit.

`task=` picks what is evaluated: `text2motion` (the default: all of the above) or one of the
paper's editing benchmarks, inbetween|outpaint|prefix|suffix|upper-body|long (editing.py; the
`editing:` settings), run named `evaluate-<task>-<data>-<time>`, metrics `edit/<task>/<metric>`
(`edit/<task>-without-text/<metric>` for a temporal task with editing.with_text=false; the
upper-body lower-mask sweep also as `edit/upper-body/sweep/<metric>` by step = mask in percent),
its tables in evaluation.md/json and the sweep's plot as an artifact.

Every task also renders `samples` captions of the split, each real motion above what the model made
of it (`long`: one long motion of `editing.long_prompts` captions under their real motions;
samples.py): `samples.gif` and `samples.png` in output_dir and the run's `samples/`.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import defaultdict
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from mlflow.entities import Metric
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig

from mmm.config import to_object
from mmm.data.humanml3d import load_stats
from mmm.data.synthetic.adherence import check_motion
from mmm.device import check_device
from mmm.evaluation.adherence import adherence_metrics, parts_in_span, prompt_adherence
from mmm.evaluation.configs import EvaluateConfig, check_samples
from mmm.evaluation.editing import TASKS, check_task_model, evaluate_editing, task_label
from mmm.evaluation.evaluators import load_evaluator, load_judge
from mmm.evaluation.metrics import fid
from mmm.evaluation.protocol import evaluate_text_to_motion, results_table
from mmm.evaluation.samples import render_samples
from mmm.fingerprint import dataset_fingerprint
from mmm.generation.model import TextToMotion
from mmm.generation.settings import check_candidates
from mmm.motion.features import recover_from_ric
from mmm.tokenizer.load import load_tokenizer
from mmm.tracking import (
    DESCRIPTION_TAG,
    artifact_location,
    log_dataset_input,
    prepare_experiment,
    resolve_tracking_uri,
    run_link,
    source_tags,
    timestamp,
    version_link,
)

log = logging.getLogger(__name__)


@torch.no_grad()
def reconstruction_metrics(
    tokenizer, evaluator, clips: dict[str, np.ndarray], batch: int = 32, labels: Path | None = None
) -> dict:
    """Stage-1 reconstruction of whole clips (cut to a multiple of 4, at most 196 frames): FID of
    the reconstructions against the clips (when an evaluator is given), and MPJPE in mm
    (root-aligned and global), of the codes `tokenizer.encode` picks ("encoding": its label); when
    that is the code search, the MPJPE of the nearest codes too (`*_nearest`), so the two can be
    compared. With `labels` (a labels/ folder), also whether each clip's actions
    are still there after the round trip: "adherence" {"rate", "per_action": {actions: (passed,
    total)}} of the reconstructions, checked like generated motions (strict, on the labelled spans)."""
    unit = tokenizer.tokenizer.cfg.downsample
    mean, std = tokenizer.mean, tokenizer.std
    by_length: dict[int, list[tuple[str, np.ndarray]]] = {}
    for motion_id, features in clips.items():
        n = min(features.shape[0], 196) // unit * unit
        if n >= unit:
            by_length.setdefault(n, []).append((motion_id, features[:n]))
    searched = tokenizer.encode_cfg.candidates > 1
    real_emb, rec_emb, frames = [], [], 0
    errors = defaultdict(float)  # summed over frames, mm: aligned, global (and of the nearest codes)
    kept: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    scale = tokenizer.skeleton.unit_scale * 1000.0

    def add_errors(j_real: torch.Tensor, j_rec: torch.Tensor, suffix: str = "") -> None:
        local = ((j_real - j_real[..., :1, :]) - (j_rec - j_rec[..., :1, :])).norm(dim=-1).mean(-1)
        errors["mpjpe_root_aligned_mm" + suffix] += float(local.sum()) * scale
        errors["mpjpe_global_mm" + suffix] += float((j_real - j_rec).norm(dim=-1).mean(-1).sum()) * scale

    for n, group in sorted(by_length.items()):
        for i in range(0, len(group), batch):
            ids = [motion_id for motion_id, _ in group[i : i + batch]]
            x = torch.from_numpy(np.stack([f for _, f in group[i : i + batch]]).astype(np.float32)).to(
                mean.device
            )
            normalized = (x - mean) / std
            rec = tokenizer.tokenizer.decode(tokenizer.encode(normalized)) * std + mean
            lengths = torch.full((len(x),), n)
            if evaluator is not None:
                real_emb.append(evaluator.embed_motions(x, lengths).cpu())
                rec_emb.append(evaluator.embed_motions(rec, lengths).cpu())
            j_real, j_rec = recover_from_ric(x.cpu()), recover_from_ric(rec.cpu())
            add_errors(j_real, j_rec)
            if searched:
                nearest = tokenizer.tokenizer.decode(tokenizer.tokenizer.encode(normalized)) * std + mean
                add_errors(j_real, recover_from_ric(nearest.cpu()), "_nearest")
            frames += j_real.shape[0] * j_real.shape[1]
            if labels is not None:
                for motion_id, joints in zip(ids, j_rec.numpy()):
                    path = labels / f"{motion_id}.json"
                    if path.exists():
                        parts = parts_in_span(json.loads(path.read_text())["parts"], 0, n)
                        if parts:
                            counts = kept["+".join(p["action"] for p in parts)]
                            counts[0] += check_motion(joints, parts).passed
                            counts[1] += 1
    result = {name: total / frames for name, total in errors.items()}
    result.update({"clips": sum(len(g) for g in by_length.values()), "encoding": tokenizer.encode_cfg.label})
    if evaluator is not None:
        result["fid"] = fid(torch.cat(real_emb), torch.cat(rec_emb))
    if kept:
        total = sum(t for _, t in kept.values())
        result["adherence"] = {
            "rate": sum(k for k, _ in kept.values()) / total,
            "count": total,
            "per_action": {k: tuple(v) for k, v in sorted(kept.items())},
        }
    return result


def evaluate(cfg_node: DictConfig) -> dict:
    """Evaluate (see the module's docstring); returns the results with `table`, `metrics` (what is
    charted), `intervals` (metric -> interval) and `run_id` (when logged)."""
    cfg: EvaluateConfig = to_object(cfg_node)
    check_device(cfg.device)
    if cfg.task not in TASKS:
        raise ValueError(f"task={cfg.task!r} is not a task; choose from {'|'.join(TASKS)}")
    cfg.editing.validate()
    unknown = set(cfg.what) - {"text2motion", "reconstruction", "adherence"}
    if unknown:
        raise ValueError(
            f"what={cfg.what}: unknown {sorted(unknown)}; choose from text2motion, reconstruction, adherence"
        )
    check_samples(cfg.samples)
    unmeasurable = adherence_unmeasurable(cfg)
    if unmeasurable and cfg.task == "text2motion" and set(cfg.what) == {"adherence"}:
        raise ValueError(
            f"what=[adherence]: {unmeasurable}; on this dataset ask for what=[text2motion,reconstruction]"
        )
    tracking_uri = resolve_tracking_uri(cfg.logger.tracking_uri)
    run = _EvaluationRun(cfg, tracking_uri) if cfg.logger.enabled else None
    try:
        results = _evaluate(cfg, tracking_uri, run, unmeasurable)
        if run is not None:
            run.finish(results, Path(cfg.output_dir))
    except BaseException as error:
        if run is not None:
            run.fail(error)
        raise
    return results


def adherence_unmeasurable(cfg: EvaluateConfig) -> str | None:
    """Why the prompt adherence `what` asks for cannot be measured on the data (None: it can, or is
    not asked for, or the folder does not exist yet: the synthetic default is written with labels)."""
    root = Path(cfg.data.root)
    if "adherence" not in cfg.what or not root.is_dir() or (root / "labels").is_dir():
        return None
    return (
        f"prompt adherence not measured: {root} has no labels/ folder (the action labels the synthetic "
        "dataset writes, which the adherence check reads)"
    )


def _evaluate(
    cfg: EvaluateConfig, tracking_uri: str, run: "_EvaluationRun | None", unmeasurable: str | None
) -> dict:
    """The evaluation; `unmeasurable`: why prompt adherence cannot be measured (adherence_unmeasurable)."""
    editing = cfg.task != "text2motion"
    check_candidates(cfg.adherence_candidates, "adherence_candidates")
    # parts=True: with no model named, upper-body edits default to the part-aware champion.
    model = TextToMotion.load(
        cfg.text2motion,
        tracking_uri,
        device=cfg.device,
        parts=cfg.task == "upper-body",
        stage1=cfg.stage1,
        precision=cfg.precision,
    )
    if editing:
        check_task_model(cfg.task, model)  # before the evaluator and data: the model is the usual mistake
    evaluator = (
        load_evaluator(
            cfg.evaluator.reference, tracking_uri, cfg.device, cfg.evaluator.glove_dir, cfg.evaluator.norm_dir
        )
        if editing or {"text2motion", "reconstruction"} & set(cfg.what)
        else None
    )
    root = Path(cfg.data.root)
    items, _ = cfg.data.items(cfg.split, root)
    results: dict = {
        "text2motion_model": model.identity,
        "precision": model.precision,
        "evaluator": getattr(evaluator, "identity", None),
        "split": cfg.split,
        "data_fingerprint": dataset_fingerprint(root),
    }
    if run is not None:
        run.started(results, root)
    if unmeasurable:
        log.warning("%s", unmeasurable)
        results["adherence_not_measured"] = unmeasurable
    samples = render_samples(
        model,
        cfg.task,
        items,
        root,
        Path(cfg.output_dir),
        cfg.samples,
        cfg.editing,
        cfg.protocol.sampling,
        cfg.protocol.seed,
    )
    results["samples"] = [str(path) for path in samples]
    if editing:
        return _evaluate_editing(cfg, model, evaluator, items, root, results)
    metrics: dict[str, float] = {}
    intervals: dict[str, float] = {}
    tables = []
    if "text2motion" in cfg.what:
        mean, std = load_stats(root, cfg.data.feature_dim)
        proto = evaluate_text_to_motion(model, evaluator, items, mean, std, cfg.protocol)
        results["text2motion"] = {k: proto[k] for k in ("generated", "real")}
        for which in ("generated", "real"):
            for metric, (value, ci) in proto[which].items():
                if not math.isnan(value):
                    metrics[f"{which}/{metric}"], intervals[f"{which}/{metric}"] = value, ci
        tables.append(
            results_table(
                {"Real motion": proto["real"], "Generated": proto["generated"]},
                f"Text-to-motion on {cfg.data.name} {cfg.split}, {cfg.protocol.replications} replications, "
                f"evaluator {evaluator.identity}",
            )
        )
    if "reconstruction" in cfg.what:
        tokenizer = (
            model.tokenizer
            if cfg.tokenizer is None
            else load_tokenizer(cfg.tokenizer, tracking_uri)[0].to(cfg.device)
        )
        clips, _ = cfg.data.clips(cfg.split, root)
        labels = root / "labels" if (root / "labels").is_dir() else None
        recon = reconstruction_metrics(tokenizer, evaluator, clips, labels=labels)
        results["reconstruction"] = recon
        metrics.update(
            {f"recon/{k}": float(v) for k, v in recon.items() if k not in ("clips", "adherence", "encoding")}
        )
        fid_text = f"FID {recon['fid']:.4f}, " if "fid" in recon else ""
        kept = recon.get("adherence")
        if kept:
            metrics["recon/adherence_rate"] = kept["rate"]
        tables.append(
            f"**Reconstruction ({recon['clips']} {cfg.split} clips)**: {fid_text}MPJPE "
            f"{recon['mpjpe_root_aligned_mm']:.1f} mm (root-aligned), "
            f"{recon['mpjpe_global_mm']:.1f} mm (global), codes by {recon['encoding']}"
            + (
                f" (the nearest codes: {recon['mpjpe_root_aligned_mm_nearest']:.1f} / "
                f"{recon['mpjpe_global_mm_nearest']:.1f} mm)"
                if "mpjpe_global_mm_nearest" in recon
                else ""
            )
            + (f"; the labelled actions still there after the round trip: {kept['rate']:.3f}" if kept else "")
        )
    if "adherence" in cfg.what and (root / "labels").is_dir():
        candidates = cfg.adherence_candidates
        judge = load_judge(cfg.adherence_judge, tracking_uri, cfg.device) if candidates > 1 else None
        adherence = prompt_adherence(
            model,
            root,
            items,
            cfg.protocol.sampling,
            cfg.protocol.seed,
            max_items=cfg.adherence_max_items,
            candidates=candidates,
            judge=judge,
            by_clause=cfg.adherence_by_clause,
            counterfactuals=cfg.adherence_counterfactuals,
        )
        if judge is not None:
            results["adherence_judge"] = {
                "candidates": candidates,
                "identity": judge.identity,
                "by_clause": cfg.adherence_by_clause,
                "counterfactuals": cfg.adherence_counterfactuals,
            }
        results["adherence"] = adherence
        # Best of N gets its own keys: a plain run and a judged one are not the same measurement.
        metrics.update(
            adherence_metrics(adherence, "adherence" if judge is None else f"adherence_best{candidates}")
        )
        groups = ", ".join(
            f"{name} {g['strict']:.3f} strict / {g['ordered']:.3f} in order ({g['count']})"
            for name, g in adherence["groups"].items()
        )
        refinements = [
            name
            for name, on in (
                ("clause by clause", cfg.adherence_by_clause),
                ("against counterfactuals", cfg.adherence_counterfactuals),
            )
            if on
        ]
        how = ", " + (" and ".join(refinements) or "whole captions only")
        lines = [
            "**Prompt adherence**"
            + (f" (best of {candidates} by {judge.identity}{how})" if judge is not None else "")
            + f": {adherence['rate']:.3f} strict (each action inside its labelled span), "
            f"{adherence['ordered_rate']:.3f} order-aware (the actions in the caption's order, wherever they "
            f"meet) of {adherence['count']} {cfg.split} captions ({adherence['skipped']} without a checkable "
            f"label); {groups}",
            "",
            "| actions | strict | in order | of | kept by the tokenizer (clips) |",
            "|---|---|---|---|---|",
        ]
        ordered = adherence["per_action_ordered"]
        kept = results.get("reconstruction", {}).get("adherence", {}).get("per_action", {})
        lines += [
            f"| {k} | {a} | {ordered[k][0]} | {b} | {f'{kept[k][0]} of {kept[k][1]}' if k in kept else '-'} |"
            for k, (a, b) in adherence["per_action"].items()
        ]
        tables.append("\n".join(lines))
    elif unmeasurable:
        tables.append(f"**Prompt adherence**: {unmeasurable.removeprefix('prompt adherence ')}.")
    table = "\n\n".join(tables)
    out_dir = Path(cfg.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "evaluation.md").write_text(table + "\n")
    (out_dir / "evaluation.json").write_text(json.dumps(results, indent=2, default=str))
    results["table"] = table
    results["metrics"] = metrics
    results["intervals"] = intervals
    return results


def _evaluate_editing(cfg: EvaluateConfig, model, evaluator, items, root: Path, results: dict) -> dict:
    """One editing task (editing.py); `what` only says whether the labelled checks run (adherence)."""
    mean, std = load_stats(root, cfg.data.feature_dim)
    out_dir = Path(cfg.output_dir)
    task = evaluate_editing(
        cfg.task,
        model,
        evaluator,
        items,
        mean,
        std,
        cfg.protocol,
        cfg.editing,
        root,
        out_dir,
        adherence="adherence" in cfg.what,
        max_items=cfg.adherence_max_items,
        title=f"{cfg.data.name} {cfg.split}, evaluator {evaluator.identity}",
        split=cfg.split,
    )
    results[cfg.task] = task["results"]
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "evaluation.md").write_text(task["table"] + "\n")
    (out_dir / "evaluation.json").write_text(json.dumps(results, indent=2, default=str))
    results.update(
        table=task["table"],
        metrics=task["metrics"],
        intervals=task["intervals"],
        series=task["series"],
        artifacts=task["artifacts"],
    )
    return results


class _EvaluationRun:
    """The evaluation's MLflow run, created before the work starts (through the client: no
    process-wide active run) and ended with it."""

    def __init__(self, cfg: EvaluateConfig, tracking_uri: str):
        self.cfg, self.client = cfg, MlflowClient(tracking_uri)
        # no task in the default task's name (as it always was)
        task = "" if cfg.task == "text2motion" else f"{task_label(cfg.task, cfg.editing)}-"
        experiment_id = prepare_experiment(
            self.client, cfg.logger.experiment, artifact_location(tracking_uri, cfg.logger.artifact_root)
        )
        run = self.client.create_run(
            experiment_id,
            run_name=cfg.logger.run_name or f"evaluate-{task}{cfg.data.name}-{timestamp()}",
            tags={"mmm.stage": "evaluation", "split": cfg.split, **source_tags("mmm evaluate")},
        )
        self.run_id = run.info.run_id
        params = {
            "task": cfg.task,
            "replications": cfg.protocol.replications,
            "what": ",".join(cfg.what),
            "precision": cfg.precision or "default",
            "sampling": json.dumps(asdict(cfg.protocol.sampling))[:500],
        }
        if cfg.task != "text2motion":
            params["editing"] = json.dumps(asdict(cfg.editing))[:500]
        for key, value in params.items():
            self.client.log_param(self.run_id, key, value)

    def started(self, results: dict, root: Path) -> None:
        """The model, evaluator and data are known: tag them and record the dataset input."""
        identity = results["text2motion_model"]
        for key, value in {
            "text2motion.reference": identity.get("reference") or "",
            "text2motion.run_id": identity.get("run_id") or "",
            "evaluator": results["evaluator"] or "",
            "data.fingerprint": results["data_fingerprint"],
        }.items():
            self.client.set_tag(self.run_id, key, str(value))
        log_dataset_input(
            self.client,
            self.run_id,
            self.cfg.data.name,
            root,
            results["data_fingerprint"],
            context="evaluation",
        )

    def finish(self, results: dict, out_dir: Path) -> None:
        now = int(time.time() * 1000)
        metrics = [Metric(k, float(v), now, 0) for k, v in results["metrics"].items()]
        metrics += [
            Metric(k, float(v), now, step)
            for k, points in results.get("series", {}).items()
            for step, v in points
            if math.isfinite(v)
        ]
        for i in range(0, len(metrics), 500):
            self.client.log_batch(self.run_id, metrics=metrics[i : i + 500])
        self.client.log_artifact(self.run_id, str(out_dir / "evaluation.md"))
        self.client.log_artifact(self.run_id, str(out_dir / "evaluation.json"))
        for path in results.get("artifacts", []):
            self.client.log_artifact(self.run_id, str(path))
        for path in results.get("samples", []):
            self.client.log_artifact(self.run_id, path, "samples")
        self.client.set_tag(self.run_id, DESCRIPTION_TAG, self.description(results))
        self.client.set_terminated(self.run_id, "FINISHED")
        results["run_id"] = self.run_id

    def fail(self, error: BaseException) -> None:
        try:
            message = " ".join(str(error).split())[:500] or type(error).__name__
            self.client.set_tag(
                self.run_id, DESCRIPTION_TAG, f"### Evaluation failed\n\n`{type(error).__name__}`: {message}"
            )
            self.client.set_terminated(self.run_id, "FAILED")
        except Exception:  # the store itself may be what failed: the original error matters
            log.exception("could not mark evaluation run %s as failed", self.run_id)

    def description(self, results: dict) -> str:
        """Markdown: what was evaluated (with links to the model's run and registered version) and the
        table."""
        identity = results["text2motion_model"]
        model = self._model_links(identity)
        evaluator = f", evaluator `{results['evaluator']}`" if results.get("evaluator") else ""
        return "\n".join(
            [
                f"### Evaluation of {model}",
                "",
                f"On {self.cfg.data.name} {self.cfg.split} (data "
                f"`{results['data_fingerprint']}`){evaluator}; "
                "± is the 95% confidence interval over the replications (1.96·std/sqrt(n)).",
                "",
                results["table"],
            ]
        )

    def _model_links(self, identity: dict) -> str:
        parts = []
        run_id = identity.get("run_id")
        if run_id:
            try:
                run = self.client.get_run(run_id)
                parts.append(
                    "the model of run "
                    f"{run_link(run.info.experiment_id, run_id, run.info.run_name or run_id)}"
                )
            except MlflowException:
                parts.append(f"the model of run `{run_id}`")
        else:
            parts.append(f"`{identity.get('reference')}`")
        versions = []
        reference = identity.get("reference") or ""
        if reference.startswith("models:/") and identity.get("version") is not None:
            body = reference[len("models:/") :]
            name = body.split("@", 1)[0] if "@" in body else body.rsplit("/", 1)[0]
            versions.append((name, str(identity["version"])))
        elif run_id:
            try:
                found = self.client.search_model_versions(f"run_id = '{run_id}'")
            except MlflowException:
                found = []
            versions += [(v.name, str(v.version)) for v in found]
        if versions:
            parts.append("registered as " + ", ".join(version_link(n, v) for n, v in sorted(set(versions))))
        return ", ".join(parts)

"""Run pipeline steps as one MLflow parent run with a nested run per step, skipping unchanged ones.

A step's key is a hash of what determines its result (its resolved config, the code version, the
content fingerprint of the data it reads, the outputs it consumes); the key and the step's outputs
are kept in a state file, which one pipeline at a time uses (a lock beside it). A rerun skips a
step whose key is unchanged and whose outputs still exist, and runs the rest: a failed pipeline
restarts at the step that failed. Runs are created through the MLflow client, not the fluent
API, so the steps' own runs (training, evaluation, promotion) start freely inside.

In the dashboard: the parent run `pipeline-<name>-<time>` (tagged with the git commit, the data as
its dataset input) has nested runs `01-<step>`, `02-<step>`, ... (tag `mmm.step.order`). At the end,
failed or not, the parent's description lists the steps in order with their status, duration and
links (the nested run, the step's own training or evaluation run, the version a promotion
registered with its alias and reason), and the parent's metrics are the steps' reported metrics
prefixed by the step (`stage1/val/...`, `evaluate/generated/fid`) with `pipeline/seconds` and
`pipeline/steps_ran|skipped|failed`.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from mlflow.entities import Metric
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from mmm.tracking import (
    DESCRIPTION_TAG,
    artifact_location,
    log_dataset_input,
    prepare_experiment,
    run_link,
    source_tags,
    timestamp,
    version_link,
)

log = logging.getLogger(__name__)


@dataclass
class Step:
    name: str
    inputs: Callable[["Context"], dict]  # what determines the result (JSON-serializable)
    run: Callable[["Context"], dict]  # does the work; returns outputs (run ids, paths, metrics)
    valid: Callable[["Context", dict], bool] = lambda ctx, outputs: True  # are stored outputs still usable


@dataclass
class Context:
    cfg: object  # PipelineConfig
    tracking_uri: str
    shared_overrides: list[str] = field(default_factory=list)  # data.*/logger.* overrides every step takes
    outputs: dict[str, dict] = field(default_factory=dict)  # step name -> outputs, as the run goes


@dataclass
class StepReport:
    name: str
    status: str  # ran | skipped | failed
    seconds: float
    outputs: dict
    run_id: str | None = None  # the step's nested run
    order: int = 0  # 1-based position in the pipeline
    error: str | None = None  # failed: the exception, on one line


def step_key(name: str, inputs: dict) -> str:
    return hashlib.sha256(
        json.dumps({"step": name, **inputs}, sort_keys=True, default=str).encode()
    ).hexdigest()[:16]


def _load_state(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _save_state(path: Path, state: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(state, indent=2, default=str))
    os.replace(tmp, path)


@contextmanager
def state_lock(state_file: Path):
    """Serialize pipelines that share `state_file`: an exclusive flock on `<state_file>.lock`, held
    for the whole run (a second pipeline waits, then sees the first one's state)."""
    state_file.parent.mkdir(parents=True, exist_ok=True)
    with open(state_file.with_name(state_file.name + ".lock"), "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.warning("another pipeline is running on %s: waiting for it to finish", state_file)
            fcntl.flock(handle, fcntl.LOCK_EX)
        yield  # closing the file releases the lock


def _flat(outputs: dict) -> dict[str, str]:
    return {f"output.{k}": str(v)[:500] for k, v in outputs.items() if not isinstance(v, dict)}


def _one_line(text: object, limit: int = 300) -> str:
    """Text for a markdown table cell: one line, no column separators, at most `limit` characters."""
    line = " ".join(str(text).split()).replace("|", "\\|")
    return line if len(line) <= limit else line[: limit - 1] + "…"


class _Links:
    """Markdown links to runs and versions, each run looked up once (its experiment and name)."""

    def __init__(self, client):
        self.client, self.runs = client, {}

    def run(self, run_id: str | None, text: str | None = None) -> str:
        if not run_id:
            return ""
        if run_id not in self.runs:
            try:
                self.runs[run_id] = self.client.get_run(run_id).info
            except MlflowException:
                self.runs[run_id] = None
        info = self.runs[run_id]
        if info is None:
            return f"`{run_id}` (deleted)"
        return run_link(info.experiment_id, run_id, text or info.run_name or run_id)

    @staticmethod
    def version(outputs: dict) -> str:
        if outputs.get("version") in (None, ""):
            return ""
        return (
            version_link(outputs["model"], outputs["version"])
            if outputs.get("model")
            else f"version {outputs['version']}"
        )


def _step_description(report: StepReport, parent_link: str, links: _Links, finished: str | None) -> str:
    """The nested step run's markdown: what the step did and where its result is."""
    head = f"Step {report.order:02d} of pipeline {parent_link}: **{report.name}**"
    if report.status == "failed":
        lines = [
            f"{head}, failed after {report.seconds:.1f} s: {_one_line(report.error or '', 1000)} (the "
            "traceback is in `error.txt`)."
        ]
    elif report.status == "skipped":
        lines = [
            f"{head}, skipped: its inputs are unchanged since {finished or 'an earlier run'} (`step.key`), "
            "its outputs are reused."
        ]
    else:
        lines = [f"{head}, ran in {report.seconds:.1f} s."]
    own = links.run(report.outputs.get("run_id"))
    if own:
        lines += ["", f"Its run: {own}"]
    version = links.version(report.outputs)
    if version:
        lines += [
            "",
            f"Registered {version} with alias `{report.outputs.get('alias', '?')}`: "
            f"{_one_line(report.outputs.get('reason', ''), 1000)}",
        ]
    return "\n".join(lines)


def _pipeline_description(
    name: str, steps: list[Step], reports: list[StepReport], status: str, seconds: float, links: _Links
) -> str:
    """The parent run's markdown: a title line, then one row per step in execution order."""
    counts = {s: sum(r.status == s for r in reports) for s in ("ran", "skipped", "failed")}
    outcome = "finished" if status == "FINISHED" else "failed"
    title = (
        f"### Pipeline `{name}` {outcome} in {seconds:.1f} s: {counts['ran']} ran, {counts['skipped']} "
        "skipped" + (f", {counts['failed']} failed" if counts["failed"] else "") + f" of {len(steps)} steps"
    )
    lines = [
        title,
        "",
        "| # | step | status | seconds | run | registered version | alias | reason |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in reports:
        lines.append(
            f"| {r.order:02d} | {links.run(r.run_id, r.name)} | {r.status} | {r.seconds:.1f} | "
            f"{links.run(r.outputs.get('run_id'))} | "
            f"{links.version(r.outputs)} | {r.outputs.get('alias') or ''} | "
            f"{_one_line(r.outputs.get('reason') or '')} |"
        )
    for order, step in enumerate(steps[len(reports) :], len(reports) + 1):
        lines.append(f"| {order:02d} | {step.name} | not run | | | | | |")
    failed = next((r for r in reports if r.status == "failed"), None)
    if failed is not None:
        lines += [
            "",
            f"**Failed at {failed.order:02d} {failed.name}**: {_one_line(failed.error or '', 1000)} (its "
            "run's `error.txt` has the traceback).",
        ]
    lines += [
        "",
        "The step column links each step's nested run; the run column the step's own training or evaluation "
        "run.",
    ]
    return "\n".join(lines)


def _headline_metrics(reports: list[StepReport], seconds: float) -> dict[str, float]:
    """The steps' reported metrics prefixed by the step, and the pipeline's own counts."""
    metrics = {}
    for r in reports:
        for k, v in (r.outputs.get("metrics") or {}).items():
            if not k.endswith(
                "_ci"
            ):  # intervals belong to tables (an evaluation from an older state may report them)
                metrics[f"{r.name}/{k}"] = float(v)
    metrics["pipeline/seconds"] = seconds
    for status in ("ran", "skipped", "failed"):
        metrics[f"pipeline/steps_{status}"] = float(sum(r.status == status for r in reports))
    return metrics


def run_steps(
    name: str,
    steps: list[Step],
    ctx: Context,
    state_file: Path,
    force: set[str] = frozenset(),
    experiment: str = "mmm-pipeline",
    artifact_root: str = "mlartifacts",
    dataset: Callable[[Context], tuple[str, str, str] | None] | None = None,
) -> list[StepReport]:
    """Run `steps` in order under one parent run. `dataset`: (name, root, fingerprint) of the data
    the pipeline reads, recorded as the parent run's dataset input. Pipelines on one state file
    run one at a time (`state_lock`)."""
    with state_lock(state_file):
        return _run_steps(name, steps, ctx, state_file, force, experiment, artifact_root, dataset)


def _run_steps(
    name: str,
    steps: list[Step],
    ctx: Context,
    state_file: Path,
    force: set[str],
    experiment: str,
    artifact_root: str,
    dataset: Callable[[Context], tuple[str, str, str] | None] | None,
) -> list[StepReport]:
    client = MlflowClient(ctx.tracking_uri)
    experiment_id = prepare_experiment(client, experiment, artifact_location(ctx.tracking_uri, artifact_root))
    parent = client.create_run(
        experiment_id,
        run_name=f"pipeline-{name}-{timestamp()}",
        tags={"mmm.pipeline": name, **source_tags(f"mmm pipeline {name}")},
    )
    parent_id = parent.info.run_id
    parent_link = run_link(experiment_id, parent_id, parent.info.run_name)
    links = _Links(client)
    state = _load_state(state_file)
    reports: list[StepReport] = []
    status = "FINISHED"
    pipeline_started = time.perf_counter()
    try:
        data = dataset(ctx) if dataset is not None else None
        if data is not None:
            log_dataset_input(client, parent_id, *data, context="pipeline")
        for order, step in enumerate(steps, 1):
            child = client.create_run(
                experiment_id,
                run_name=f"{order:02d}-{step.name}",
                tags={
                    "mlflow.parentRunId": parent_id,
                    "mmm.pipeline": name,
                    "mmm.step": step.name,
                    "mmm.step.order": str(order),
                },
            )
            child_id = child.info.run_id
            started = time.perf_counter()
            inputs, previous, reuse = {}, {}, False
            try:
                # Inside the step's run: composing its config (part of its key) fails on a bad override like
                # the step itself.
                inputs = step.inputs(ctx)
                key = step_key(step.name, inputs)
                client.set_tag(child_id, "step.key", key)
                previous = state.get(step.name, {})
                reuse = (
                    step.name not in force
                    and previous.get("key") == key
                    and step.valid(ctx, previous.get("outputs", {}))
                )
                if reuse:
                    outputs = previous["outputs"]
                    log.info("pipeline %s: %s unchanged (key %s), skipped", name, step.name, key)
                else:
                    log.info("pipeline %s: running %s", name, step.name)
                    outputs = step.run(ctx)
                    state[step.name] = {
                        "key": key,
                        "outputs": outputs,
                        "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
                    }
                    _save_state(state_file, state)
            except BaseException as error:
                report = StepReport(
                    step.name,
                    "failed",
                    time.perf_counter() - started,
                    {},
                    child_id,
                    order,
                    f"{type(error).__name__}: {' '.join(str(error).split())}",
                )
                reports.append(report)
                client.set_tag(child_id, "step.status", "failed")
                client.log_text(child_id, traceback.format_exc(), "error.txt")
                client.set_tag(child_id, DESCRIPTION_TAG, _step_description(report, parent_link, links, None))
                client.set_terminated(child_id, "FAILED")
                raise
            seconds = time.perf_counter() - started
            ctx.outputs[step.name] = outputs
            report = StepReport(step.name, "skipped" if reuse else "ran", seconds, outputs, child_id, order)
            for k, v in {"step.status": report.status, **_flat(outputs)}.items():
                client.set_tag(child_id, k, v)
            client.set_tag(
                child_id,
                DESCRIPTION_TAG,
                _step_description(report, parent_link, links, previous.get("finished") if reuse else None),
            )
            for k, v in json.loads(json.dumps(inputs, default=str)).items():
                client.log_param(child_id, f"input.{k}", str(v)[:500])
            for k, v in (outputs.get("metrics") or {}).items():
                client.log_metric(child_id, k, float(v))
            client.log_metric(child_id, "seconds", seconds)
            client.set_terminated(child_id, "FINISHED")
            reports.append(report)
    except BaseException:
        status = "FAILED"
        raise
    finally:
        seconds = time.perf_counter() - pipeline_started
        try:
            summary = "\n".join(f"{r.name:22s} {r.status:8s} {r.seconds:8.1f} s" for r in reports)
            client.log_text(parent_id, summary + "\n", "steps.txt")
            now = int(time.time() * 1000)
            metrics = [Metric(k, v, now, 0) for k, v in _headline_metrics(reports, seconds).items()]
            for i in range(0, len(metrics), 500):
                client.log_batch(parent_id, metrics=metrics[i : i + 500])
            client.set_tag(
                parent_id,
                DESCRIPTION_TAG,
                _pipeline_description(name, steps, reports, status, seconds, links),
            )
        except Exception:
            if status == "FINISHED":
                client.set_terminated(parent_id, "FAILED")
                raise
            log.exception(
                "pipeline %s: could not record the failed run's summary", name
            )  # the step's error is what propagates
        client.set_terminated(parent_id, status)
    return reports

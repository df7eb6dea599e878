"""Run pipeline steps as one MLflow parent run with a nested run per step, skipping unchanged ones.

A step's key is a hash of what determines its result (its overrides, the data fingerprint, the
outputs it consumes); the key and the step's outputs are kept in a state file. A rerun skips a
step whose key is unchanged and whose outputs still exist, and runs the rest: a failed pipeline
restarts at the step that failed. Runs are created through the MLflow client, not the fluent
API, so the steps' own runs (training, evaluation, promotion) start freely inside.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

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
    run_id: str | None = None


def step_key(name: str, inputs: dict) -> str:
    return hashlib.sha256(json.dumps({"step": name, **inputs}, sort_keys=True, default=str).encode()).hexdigest()[:16]


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


def _flat(outputs: dict) -> dict[str, str]:
    return {f"output.{k}": str(v)[:500] for k, v in outputs.items() if not isinstance(v, dict)}


def run_steps(name: str, steps: list[Step], ctx: Context, state_file: Path, force: set[str] = frozenset(), experiment: str = "mmm-pipeline", artifact_root: str = "mlartifacts") -> list[StepReport]:
    from mlflow.tracking import MlflowClient

    from mmm.training.common import artifact_location

    client = MlflowClient(ctx.tracking_uri)
    found = client.get_experiment_by_name(experiment)
    experiment_id = found.experiment_id if found else client.create_experiment(experiment, artifact_location=artifact_location(ctx.tracking_uri, artifact_root))
    parent = client.create_run(experiment_id, run_name=f"pipeline-{name}", tags={"mmm.pipeline": name})
    state = _load_state(state_file)
    reports: list[StepReport] = []
    status = "FINISHED"
    try:
        for step in steps:
            inputs = step.inputs(ctx)
            key = step_key(step.name, inputs)
            previous = state.get(step.name, {})
            reuse = step.name not in force and previous.get("key") == key and step.valid(ctx, previous.get("outputs", {}))
            child = client.create_run(experiment_id, run_name=step.name, tags={"mlflow.parentRunId": parent.info.run_id, "mmm.pipeline": name, "step.key": key})
            started = time.perf_counter()
            try:
                if reuse:
                    outputs = previous["outputs"]
                    log.info("pipeline %s: %s unchanged (key %s), skipped", name, step.name, key)
                else:
                    log.info("pipeline %s: running %s", name, step.name)
                    outputs = step.run(ctx)
                    state[step.name] = {"key": key, "outputs": outputs, "finished": time.strftime("%Y-%m-%d %H:%M:%S")}
                    _save_state(state_file, state)
            except BaseException:
                client.set_tag(child.info.run_id, "step.status", "failed")
                client.log_text(child.info.run_id, traceback.format_exc(), "error.txt")
                client.set_terminated(child.info.run_id, "FAILED")
                reports.append(StepReport(step.name, "failed", time.perf_counter() - started, {}, child.info.run_id))
                raise
            seconds = time.perf_counter() - started
            ctx.outputs[step.name] = outputs
            for k, v in {"step.status": "skipped" if reuse else "ran", **_flat(outputs)}.items():
                client.set_tag(child.info.run_id, k, v)
            for k, v in json.loads(json.dumps(inputs, default=str)).items():
                client.log_param(child.info.run_id, f"input.{k}", str(v)[:500])
            for k, v in (outputs.get("metrics") or {}).items():
                client.log_metric(child.info.run_id, k, float(v))
            client.log_metric(child.info.run_id, "seconds", seconds)
            client.set_terminated(child.info.run_id, "FINISHED")
            reports.append(StepReport(step.name, "skipped" if reuse else "ran", seconds, outputs, child.info.run_id))
    except BaseException:
        status = "FAILED"
        raise
    finally:
        summary = "\n".join(f"{r.name:22s} {r.status:8s} {r.seconds:8.1f} s" for r in reports)
        client.log_text(parent.info.run_id, summary + "\n", "steps.txt")
        client.set_terminated(parent.info.run_id, status)
    return reports

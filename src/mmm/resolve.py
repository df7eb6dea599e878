"""Resolve a model reference to a local checkpoint: a path, an MLflow run, a registered model, or the newest.

    path/to/best.ckpt                 a Lightning checkpoint
    runs:/<run_id>  or  <run_id>      that run's checkpoints/best.ckpt artifact
    models:/<name>@<alias>            a registered model version (e.g. models:/mmm-text2motion@champion)
    models:/<name>/<version>
    None                              the newest finished run of the stage's experiment that has a
                                      checkpoint, else the newest <output_dir>/*/checkpoints/best.ckpt
Artifacts are downloaded once into a cache folder; nothing is fetched from outside the tracking store.
"""

from __future__ import annotations

import re
from pathlib import Path

_RUN_ID = re.compile(r"^[0-9a-f]{32}$")


class ModelNotFound(FileNotFoundError):
    pass


def download_artifact(tracking_uri: str, run_id: str, artifact_path: str, cache_dir: str | Path) -> str:
    import mlflow.artifacts

    dst = Path(cache_dir) / run_id
    local = dst / artifact_path
    if local.exists():
        return str(local)
    dst.mkdir(parents=True, exist_ok=True)
    return mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=artifact_path, dst_path=str(dst), tracking_uri=tracking_uri)


def newest_run_checkpoint(tracking_uri: str, experiment: str, cache_dir: str | Path) -> tuple[str, str] | None:
    """(run id, local best.ckpt) of the newest finished run of `experiment` that has one."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri)
    found = client.get_experiment_by_name(experiment)
    if found is None:
        return None
    for run in client.search_runs([found.experiment_id], "attributes.status = 'FINISHED'", order_by=["attributes.start_time DESC"], max_results=20):
        names = {f.path for f in client.list_artifacts(run.info.run_id, "checkpoints")}
        if "checkpoints/best.ckpt" in names:
            return run.info.run_id, download_artifact(tracking_uri, run.info.run_id, "checkpoints/best.ckpt", cache_dir)
    return None


def registered_version(reference: str, tracking_uri: str):
    """The ModelVersion of models:/NAME@ALIAS or models:/NAME/VERSION (ModelNotFound otherwise)."""
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri)
    body = reference[len("models:/"):]
    try:
        if "@" in body:
            name, alias = body.split("@", 1)
            return client.get_model_version_by_alias(name, alias)
        name, number = body.rsplit("/", 1)
        return client.get_model_version(name, number)
    except (MlflowException, ValueError) as e:
        detail = e.message.splitlines()[0] if isinstance(e, MlflowException) else str(e)
        raise ModelNotFound(f"{reference}: no such registered model version at {tracking_uri} ({detail}); `mmm models list` shows what exists") from None


def resolve_checkpoint(
    reference: str | None,
    tracking_uri: str,
    experiment: str,
    output_dir: str,
    what: str,
    train_hint: str,
    option: str,
    cache_dir: str = "outputs/cache/models",
) -> tuple[str, str, str | None]:
    """(resolved reference, local checkpoint path, run id or None)."""
    if reference is None:
        found = newest_run_checkpoint(tracking_uri, experiment, cache_dir)
        if found:
            return f"runs:/{found[0]}", found[1], found[0]
        local = sorted(Path(output_dir).glob("*/checkpoints/best.ckpt"), key=lambda p: p.stat().st_mtime)
        if local:
            return str(local[-1]), str(local[-1]), None
        raise ModelNotFound(
            f"no {what} to use: no finished run with a checkpoint in MLflow experiment {experiment!r} at {tracking_uri} "
            f"and no {output_dir}/*/checkpoints/best.ckpt; run `{train_hint}` first or name one with {option}=PATH|RUN_ID|models:/NAME@ALIAS"
        )
    if reference.startswith("models:/"):
        version = registered_version(reference, tracking_uri)
        source, run_id = version.source, version.run_id
        path = source.split(f"runs:/{run_id}/", 1)[-1] if run_id and source.startswith("runs:/") else None
        if path is None:
            raise ModelNotFound(f"{reference}: version {version.version} has source {source!r}, not a run artifact of a {what} checkpoint")
        if not path.endswith(".ckpt"):
            path = path.rstrip("/") + "/best.ckpt"
        return reference, download_artifact(tracking_uri, run_id, path, cache_dir), run_id
    run_id = reference[len("runs:/"):].strip("/") if reference.startswith("runs:/") else reference
    if _RUN_ID.match(run_id):
        return f"runs:/{run_id}", download_artifact(tracking_uri, run_id, "checkpoints/best.ckpt", cache_dir), run_id
    if not Path(reference).exists():
        raise ModelNotFound(f"{reference}: no such checkpoint file, MLflow run id or models:/ URI")
    return reference, reference, None

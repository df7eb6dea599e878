"""Resolve a model reference to a local checkpoint: a path, an MLflow run, a registered model, or the newest.

    path/to/best.ckpt                 a Lightning checkpoint
    runs:/<run_id>  or  <run_id>      that run's checkpoints/best.ckpt artifact
    models:/<name>@<alias>            a registered model version (e.g. models:/mmm-text2motion@champion)
    models:/<name>/<version>
    None                              the newest finished run of the stage's experiment that has a
                                      checkpoint, else the newest <output_dir>/*/checkpoints/best.ckpt
Nothing is fetched from outside the tracking store.

The download cache (`download_artifact`, default outputs/cache/models) is keyed by content:

    <cache>/by-sha256/<sha256 of the file>/<file name>

A run's `checkpoints/best.ckpt` is not a fixed file: a `--resume` of that run uploads a new one
under the same name, often of the same size. So the cache never trusts a run id and a path. The
package records each checkpoint's sha256 when it uploads it, as the run tag
`mmm.sha256.<artifact path>` (a registered version may carry `weights.sha256`); a lookup asks the
store for that digest and the file's size, and uses the cached file of that digest when its size
matches (a truncated file does not, and is fetched again). An artifact without a recorded digest
(uploaded by other tools) is downloaded on every lookup: nothing else says whether it changed.
A download goes into a temporary folder inside the cache folder, is checked against the store's
size and the recorded digest, and only then renamed into place, so the cache holds only complete,
verified files, and concurrent lookups never see a partial one.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path

_RUN_ID = re.compile(r"^[0-9a-f]{32}$")


class ModelNotFound(FileNotFoundError):
    pass


class ArtifactMismatch(ModelNotFound):
    """A downloaded artifact whose size or sha256 is not the one the store records."""


SHA256_TAG_PREFIX = "mmm.sha256."  # + artifact path: the run tag recording an uploaded file's sha256
VERSION_SHA256_TAG = "weights.sha256"  # a registered version's recorded digest of its checkpoint
CONTENT_FOLDER = "by-sha256"


def sha256_tag(artifact_path: str) -> str:
    return SHA256_TAG_PREFIX + artifact_path


def log_artifact_with_digest(client, run_id: str, local_path: str | Path, artifact_dir: str) -> str:
    """Upload `local_path` into the run's `artifact_dir` and record its sha256 as the run tag that
    `download_artifact` keys its cache by. The old tag is removed first, so that while the upload
    runs no reader takes the new file for the old one. Returns the digest."""
    from mlflow.exceptions import MlflowException

    from mmm.atomic import sha256_file

    artifact_path = f"{artifact_dir.rstrip('/')}/{Path(local_path).name}"
    digest = sha256_file(local_path)
    try:
        client.delete_tag(run_id, sha256_tag(artifact_path))
    except MlflowException:
        pass  # no earlier upload recorded
    client.log_artifact(run_id, str(local_path), artifact_dir)
    client.set_tag(run_id, sha256_tag(artifact_path), digest)
    return digest


def _artifact_record(client, run_id: str, artifact_path: str) -> tuple[int | None, str | None]:
    """(size in bytes the store reports or None, the run's recorded sha256 or None)."""
    from mlflow.exceptions import MlflowException

    try:
        run = client.get_run(run_id)
        parent = artifact_path.rsplit("/", 1)[0] if "/" in artifact_path else None
        listed = {f.path: f for f in client.list_artifacts(run_id, parent)}
    except MlflowException as e:
        raise ModelNotFound(f"runs:/{run_id}: no such run in the tracking store ({e.message.splitlines()[0]}); `mmm runs list` shows what exists") from None
    info = listed.get(artifact_path)
    if info is None or info.is_dir:
        have = ", ".join(sorted(p for p, f in listed.items() if not f.is_dir)) or "none"
        raise ModelNotFound(f"runs:/{run_id}/{artifact_path}: the run has no such file (files there: {have}); name a run that finished training")
    return info.file_size, run.data.tags.get(sha256_tag(artifact_path))


def _cached(cache_dir: Path, digest: str, name: str, size: int | None) -> Path | None:
    """The cached file of `digest`, when present and of the store's size."""
    path = cache_dir / CONTENT_FOLDER / digest / name
    try:
        if size is None or path.stat().st_size == size:
            return path
    except FileNotFoundError:
        return None
    return None  # truncated (or otherwise not the file): fetched again and replaced


def download_artifact(tracking_uri: str, run_id: str, artifact_path: str, cache_dir: str | Path, sha256: str | None = None) -> str:
    """A local copy of the run's artifact file, from the content-keyed cache (module docstring).
    `sha256`: the digest the caller knows the file must have (a registered version's); else the
    run's recorded one is used, where there is one. A copy whose size or digest is not the
    recorded one is refused (ArtifactMismatch, a ModelNotFound), never served."""
    import mlflow.artifacts
    from mlflow.tracking import MlflowClient

    from mmm.atomic import fsync_directory, sha256_file

    cache_dir = Path(cache_dir)
    name = artifact_path.rsplit("/", 1)[-1]
    client = MlflowClient(tracking_uri)
    problem = ""
    for _attempt in range(2):  # a second look, in case the run was uploading this file meanwhile
        size, recorded = _artifact_record(client, run_id, artifact_path)
        expected = sha256 or recorded
        if expected:
            hit = _cached(cache_dir, expected, name, size)
            if hit is not None:
                return str(hit)
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".download-", dir=cache_dir))  # same file system as the cache: the rename is atomic
        try:
            local = Path(mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=artifact_path, dst_path=str(tmp), tracking_uri=tracking_uri))
            got_size = local.stat().st_size
            digest = sha256_file(local)
            if size is not None and got_size != size:
                problem = f"the download has {got_size} bytes, the store reports {size}"
                continue
            if expected and digest != expected:
                problem = f"the download has sha256 {digest}, the recorded sha256 is {expected}"
                continue
            final = cache_dir / CONTENT_FOLDER / digest / name
            final.parent.mkdir(parents=True, exist_ok=True)
            if _cached(cache_dir, digest, name, got_size) is None:  # else another process installed it meanwhile
                os.replace(local, final)
                fsync_directory(final.parent)
            return str(final)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    raise ArtifactMismatch(
        f"runs:/{run_id}/{artifact_path}: {problem}; the artifact changed while it was read or does not match its record "
        f"(run tag {sha256_tag(artifact_path)!r} or the registered version's {VERSION_SHA256_TAG!r}); try again, and re-upload it if this persists"
    )


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


def _fetch_run_file(reference: str, tracking_uri: str, run_id: str, artifact_path: str, cache_dir: str | Path, what: str,
                    sha256: str | None = None) -> str:
    """download_artifact, with MLflow's errors (no such run, no such artifact, a store that cannot
    be reached) as a ModelNotFound naming the reference."""
    from mlflow.exceptions import MlflowException

    try:
        return download_artifact(tracking_uri, run_id, artifact_path, cache_dir, sha256=sha256)
    except ModelNotFound:
        raise  # download_artifact's own message names the run and the fix (ArtifactMismatch: not the recorded file)
    except (MlflowException, OSError) as e:
        detail = (e.message if isinstance(e, MlflowException) else str(e)).strip().splitlines()
        raise ModelNotFound(
            f"{reference}: no {what} at {tracking_uri}: run {run_id} has no artifact {artifact_path} "
            f"({detail[0][:200] if detail else type(e).__name__}); check the run id (`mmm models list`, the MLflow UI) "
            f"and --tracking-uri, or give the checkpoint file's path"
        ) from None


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
        return reference, _fetch_run_file(reference, tracking_uri, run_id, path, cache_dir, what, version.tags.get(VERSION_SHA256_TAG)), run_id
    run_id = reference[len("runs:/"):].strip("/") if reference.startswith("runs:/") else reference
    if _RUN_ID.match(run_id):
        return f"runs:/{run_id}", _fetch_run_file(reference, tracking_uri, run_id, "checkpoints/best.ckpt", cache_dir, what), run_id
    if not Path(reference).exists():
        raise ModelNotFound(f"{reference}: no such checkpoint file, MLflow run id or models:/ URI")
    return reference, reference, None

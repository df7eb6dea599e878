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

import hashlib
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import NamedTuple

import mlflow.artifacts
import torch
from mlflow.exceptions import MlflowException
from mlflow.models import Model
from mlflow.tracking import MlflowClient

from mmm.atomic import atomic_write, atomic_write_text, file_lock, fsync_directory, sha256_file
from mmm.kinds import STAGE2, ModelKind
from mmm.tracking import existing_store

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
    try:
        run = client.get_run(run_id)
        parent = artifact_path.rsplit("/", 1)[0] if "/" in artifact_path else None
        listed = {f.path: f for f in client.list_artifacts(run_id, parent)}
    except MlflowException as e:
        raise ModelNotFound(
            f"runs:/{run_id}: no such run in the tracking store ({e.message.splitlines()[0]}); `mmm "
            "dashboard` links to every experiment's runs"
        ) from None
    info = listed.get(artifact_path)
    if info is None or info.is_dir:
        have = ", ".join(sorted(p for p, f in listed.items() if not f.is_dir)) or "none"
        raise ModelNotFound(
            f"runs:/{run_id}/{artifact_path}: the run has no such file (files there: {have}); name a run "
            "that finished training"
        )
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


def download_artifact(
    tracking_uri: str, run_id: str, artifact_path: str, cache_dir: str | Path, sha256: str | None = None
) -> str:
    """A local copy of the run's artifact file, from the content-keyed cache (module docstring).
    `sha256`: the digest the caller knows the file must have (a registered version's); else the
    run's recorded one is used, where there is one. A copy whose size or digest is not the
    recorded one is refused (ArtifactMismatch, a ModelNotFound), never served."""
    cache_dir = Path(cache_dir)
    name = artifact_path.rsplit("/", 1)[-1]
    if not existing_store(tracking_uri):
        raise ModelNotFound(
            f"runs:/{run_id}: no MLflow store at {tracking_uri}; give --tracking-uri the store the run is "
            "in, or the checkpoint file's path"
        )
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
        tmp = Path(
            tempfile.mkdtemp(prefix=".download-", dir=cache_dir)
        )  # same file system as the cache: the rename is atomic
        try:
            local = Path(
                mlflow.artifacts.download_artifacts(
                    run_id=run_id, artifact_path=artifact_path, dst_path=str(tmp), tracking_uri=tracking_uri
                )
            )
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
            if (
                _cached(cache_dir, digest, name, got_size) is None
            ):  # else another process installed it meanwhile
                os.replace(local, final)
                fsync_directory(final.parent)
            return str(final)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    raise ArtifactMismatch(
        f"runs:/{run_id}/{artifact_path}: {problem}; the artifact changed while it was read or does not "
        "match its record "
        f"(run tag {sha256_tag(artifact_path)!r} or the registered version's {VERSION_SHA256_TAG!r}); try "
        "again, and re-upload it if this persists"
    )


def newest_run_checkpoint(
    tracking_uri: str, experiment: str, cache_dir: str | Path
) -> tuple[str, str] | None:
    """(run id, local best.ckpt) of the newest finished run of `experiment` that has one."""
    if not existing_store(tracking_uri):
        return None
    client = MlflowClient(tracking_uri)
    found = client.get_experiment_by_name(experiment)
    if found is None:
        return None
    for run in client.search_runs(
        [found.experiment_id],
        "attributes.status = 'FINISHED'",
        order_by=["attributes.start_time DESC"],
        max_results=20,
    ):
        names = {f.path for f in client.list_artifacts(run.info.run_id, "checkpoints")}
        if "checkpoints/best.ckpt" in names:
            return run.info.run_id, download_artifact(
                tracking_uri, run.info.run_id, "checkpoints/best.ckpt", cache_dir
            )
    return None


def registered_version(reference: str, tracking_uri: str):
    """The ModelVersion of models:/NAME@ALIAS or models:/NAME/VERSION (ModelNotFound otherwise)."""
    if not existing_store(tracking_uri):
        raise ModelNotFound(
            f"{reference}: no MLflow store at {tracking_uri}; give --tracking-uri the store the model is "
            "registered in"
        )
    client = MlflowClient(tracking_uri)
    body = reference[len("models:/") :]
    try:
        if "@" in body:
            name, alias = body.split("@", 1)
            return client.get_model_version_by_alias(name, alias)
        name, number = body.rsplit("/", 1)
        return client.get_model_version(name, number)
    except (MlflowException, ValueError) as e:
        detail = e.message.splitlines()[0] if isinstance(e, MlflowException) else str(e)
        raise ModelNotFound(
            f"{reference}: no such registered model version at {tracking_uri} ({detail}); `mmm models list` "
            "shows what exists"
        ) from None


def _fetch_run_file(
    reference: str,
    tracking_uri: str,
    run_id: str,
    artifact_path: str,
    cache_dir: str | Path,
    what: str,
    sha256: str | None = None,
) -> str:
    """download_artifact, with MLflow's errors (no such run, no such artifact, a store that cannot
    be reached) as a ModelNotFound naming the reference."""
    try:
        return download_artifact(tracking_uri, run_id, artifact_path, cache_dir, sha256=sha256)
    except ModelNotFound:
        # download_artifact's own message names the run and the fix (ArtifactMismatch: not the recorded file)
        raise
    except (MlflowException, OSError) as e:
        detail = (e.message if isinstance(e, MlflowException) else str(e)).strip().splitlines()
        raise ModelNotFound(
            f"{reference}: no {what} at {tracking_uri}: run {run_id} has no artifact {artifact_path} "
            f"({detail[0][:200] if detail else type(e).__name__}); check the run id (`mmm models list`, the "
            "MLflow UI) "
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
            f"no {what} to use: no finished run with a checkpoint in MLflow experiment {experiment!r} at "
            f"{tracking_uri} "
            f"and no {output_dir}/*/checkpoints/best.ckpt; run `{train_hint}` first or name one with "
            f"{option}=PATH|RUN_ID|models:/NAME@ALIAS"
        )
    if reference.startswith("models:/"):
        version = registered_version(reference, tracking_uri)
        source, run_id = version.source, version.run_id
        path = source.split(f"runs:/{run_id}/", 1)[-1] if run_id and source.startswith("runs:/") else None
        if path is None:
            raise ModelNotFound(
                f"{reference}: version {version.version} has source {source!r}, not a run artifact of a "
                f"{what} checkpoint"
            )
        if not path.endswith(".ckpt"):
            path = path.rstrip("/") + "/best.ckpt"
        return (
            reference,
            _fetch_run_file(
                reference, tracking_uri, run_id, path, cache_dir, what, version.tags.get(VERSION_SHA256_TAG)
            ),
            run_id,
        )
    run_id = reference[len("runs:/") :].strip("/") if reference.startswith("runs:/") else reference
    if _RUN_ID.match(run_id):
        return (
            f"runs:/{run_id}",
            _fetch_run_file(reference, tracking_uri, run_id, "checkpoints/best.ckpt", cache_dir, what),
            run_id,
        )
    if not Path(reference).exists():
        raise ModelNotFound(f"{reference}: no such checkpoint file, MLflow run id or models:/ URI")
    return reference, reference, None


def resolve_model(
    reference: str | None,
    tracking_uri: str,
    kind: ModelKind,
    option: str,
    output_dir: str | None = None,
    cache_dir: str = "outputs/cache/models",
    experiment: str | None = None,
) -> tuple[str, str, str | None]:
    """resolve_checkpoint for a model kind of the catalogue (its experiment, run folders and
    training hint); `output_dir`/`experiment` override the kind's where a config names others."""
    return resolve_checkpoint(
        reference,
        tracking_uri,
        experiment or kind.experiment,
        output_dir or kind.output_dir,
        kind.what,
        kind.train,
        option,
        cache_dir,
    )


# -- registered bundles (text-to-motion, upper-body) ----------------------------------------------
TRANSFORMER = "transformer"  # the bundle's pyfunc artifact names
TOKENIZER = "tokenizer"
JUDGE = "judge"  # the evaluator that picks among best-of-N draws (optional)
BUNDLE_CACHE = "outputs/cache/bundles"


def champion_reference(tracking_uri: str, name: str = STAGE2.registered) -> str | None:
    """models:/<name>@champion when that alias exists, else None (the newest stage-2 run)."""
    if not existing_store(tracking_uri):
        return None
    try:
        MlflowClient(tracking_uri).get_model_version_by_alias(name, "champion")
    except MlflowException:
        return None
    return f"models:/{name}@champion"


def resolve_bundle(reference: str, tracking_uri: str) -> tuple[BundleFiles, dict, object]:
    """(the bundle's local files, the identities the version's tags say they have, the
    ModelVersion) of a registered bundle models:/NAME@ALIAS or models:/NAME/VERSION."""
    version = registered_version(reference, tracking_uri)  # a clear error for an unknown name or alias
    # A registered version's files never change: one folder per (store, source) is reused.
    key = hashlib.sha256(f"{tracking_uri}|{version.source}".encode()).hexdigest()[:12]
    files = bundle_checkpoints(reference, tracking_uri, dst=Path(BUNDLE_CACHE) / key)
    # The version's tags (written when it was logged) name the weights it must hold.
    expected = {
        "transformer": version.tags.get("mmm.transformer.identity"),
        "stage1": version.tags.get("mmm.stage1.identity"),
    }
    return files, expected, version


def localize_text_files(
    transformer_checkpoint: str | Path, files: dict[str, str], dst_dir: str | Path
) -> str:
    """A copy of the stage-2 checkpoint whose text-encoder options (weights, vocab) name `files`
    instead of the training machine's paths; the weights are unchanged (the encoder's identity,
    checked on load, covers the files' content)."""
    ckpt = torch.load(transformer_checkpoint, map_location="cpu", weights_only=True)
    text = ckpt["hyper_parameters"]["text_encoder"]
    for option, path in files.items():
        text[option] = str(path)
    out = Path(dst_dir) / "transformer.local.ckpt"
    with atomic_write(out) as fh:  # a shared cache folder: other processes may be loading this file
        torch.save(ckpt, fh)
    return str(out)


def _artifact_location(model_uri: str, tracking_uri: str) -> str:
    """Where a models:/ reference's files are, asked of `tracking_uri` itself: MLflow's own
    models:/ download consults the process-wide registry instead of the one it is given."""
    if not model_uri.startswith("models:/"):
        return model_uri
    client = MlflowClient(tracking_uri, registry_uri=tracking_uri)
    body = model_uri[len("models:/") :]
    if body.startswith("m-") and "/" not in body and "@" not in body:
        return client.get_logged_model(body).artifact_location
    version = registered_version(model_uri, tracking_uri)
    return client.get_model_version_download_uri(version.name, version.version)


COMPLETE = ".complete"  # in a download folder: the bundle's folder inside it, written last


def _download(artifact_uri: str, tracking_uri: str, dst: str | Path | None) -> Path:
    """Download into `dst` (a new temporary folder when None) all or nothing: into a sibling
    first, renamed into place once complete (with its COMPLETE marker inside).

    Fills of one `dst` take turns under a lock file beside it (`.<name>.lock`); one that waited
    finds the other's complete copy and uses it. A complete copy is never deleted or replaced, so
    a process reading one is never disturbed; a `dst` without the marker was made by no fill
    (complete copies appear only by the rename) and is replaced."""
    if dst is None:
        return Path(mlflow.artifacts.download_artifacts(artifact_uri=artifact_uri, tracking_uri=tracking_uri))
    dst = Path(dst).resolve()  # MLflow answers with absolute paths
    dst.parent.mkdir(parents=True, exist_ok=True)
    with file_lock(dst.parent / f".{dst.name}.lock"):
        if not (dst / COMPLETE).is_file():  # else another process filled it while this one waited
            tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", dir=dst.parent))
            try:
                local = Path(
                    mlflow.artifacts.download_artifacts(
                        artifact_uri=artifact_uri, dst_path=str(tmp), tracking_uri=tracking_uri
                    )
                )
                atomic_write_text(tmp / COMPLETE, str(local.relative_to(tmp)))
                if dst.exists():  # not a fill's copy (see above): moved away whole, then deleted
                    stale = Path(tempfile.mkdtemp(prefix=f".{dst.name}.stale-", dir=dst.parent))
                    os.replace(dst, stale / dst.name)
                    shutil.rmtree(stale, ignore_errors=True)
                os.replace(tmp, dst)
                fsync_directory(dst.parent)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
    return dst / (dst / COMPLETE).read_text().strip()


class BundleFiles(NamedTuple):
    transformer: str  # the stage-2 checkpoint
    tokenizer: str  # the stage-1 checkpoint
    judge: str | None  # the best-of-N evaluator's checkpoint, where the bundle carries one


def bundle_checkpoints(model_uri: str, tracking_uri: str, dst: str | Path | None = None) -> BundleFiles:
    """The local files of a logged or registered bundle (models:/NAME@ALIAS, models:/NAME/VERSION,
    models:/m-ID, runs:/ID/PATH or a local folder), downloaded under `dst` (default: a new
    temporary folder). A `dst` that already holds a complete download is used as it is, so key it
    by what cannot change (a registered version, not an alias). `TextToMotion.from_files` loads
    them without MLflow's pyfunc machinery. When the bundle carries text-encoder files (CLIP), the
    stage-2 file returned is a copy pointing at them."""
    if Path(model_uri).is_dir():
        local = Path(model_uri)
    elif dst is not None and (Path(dst) / COMPLETE).is_file():
        local = Path(dst) / (Path(dst) / COMPLETE).read_text().strip()
    else:
        local = _download(_artifact_location(model_uri, tracking_uri), tracking_uri, dst)
    conf = Model.load(str(local)).flavors.get("python_function", {})
    saved = conf.get("artifacts") or {}
    if TRANSFORMER not in saved or TOKENIZER not in saved:
        raise ValueError(
            f"{model_uri}: not a text-to-motion bundle (its pyfunc artifacts are {sorted(saved) or 'none'}; "
            f"expected {TRANSFORMER!r} and {TOKENIZER!r})"
        )
    path = {name: str(local / entry["path"]) for name, entry in saved.items()}
    transformer = path[TRANSFORMER]
    text_files = {k[len("text_") :]: v for k, v in path.items() if k.startswith("text_")}
    if text_files:
        transformer = localize_text_files(transformer, text_files, local)
    return BundleFiles(transformer, path[TOKENIZER], path.get(JUDGE))

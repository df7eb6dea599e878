"""Find and load a trained tokenizer: a checkpoint path, an MLflow run, a registered model, or the newest.

Accepted references:
    path/to/best.ckpt                 a stage-1 Lightning checkpoint
    runs:/<run_id>  or  <run_id>      that run's checkpoints/best.ckpt artifact
    models:/<name>@<alias>            a registered model version (e.g. models:/mmm-tokenizer@champion)
    models:/<name>/<version>
    None                              the newest finished stage-1 run that has a checkpoint, else
                                      the newest outputs/stage1/*/checkpoints/best.ckpt
Checkpoints load with torch.load(weights_only=True).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import torch

from mmm.fingerprint import tensors_fingerprint
from mmm.tokenizer.module import TokenizerModule

STAGE1_EXPERIMENT = "mmm-stage1"
_RUN_ID = re.compile(r"^[0-9a-f]{32}$")


class ModelNotFound(FileNotFoundError):
    pass


@dataclass
class TokenizerSource:
    reference: str  # what was asked for, resolved ("runs:/...", a path, "models:/...")
    checkpoint: str  # local file
    run_id: str | None
    identity: str  # fingerprint of the tokenizer's weights and normalization


def _download(tracking_uri: str, run_id: str, artifact_path: str, cache_dir: Path) -> str:
    import mlflow.artifacts

    dst = cache_dir / run_id
    local = dst / artifact_path
    if local.exists():
        return str(local)
    dst.mkdir(parents=True, exist_ok=True)
    return mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=artifact_path, dst_path=str(dst), tracking_uri=tracking_uri)


def _newest_run_checkpoint(tracking_uri: str, cache_dir: Path) -> tuple[str, str] | None:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri)
    experiment = client.get_experiment_by_name(STAGE1_EXPERIMENT)
    if experiment is None:
        return None
    for run in client.search_runs([experiment.experiment_id], "attributes.status = 'FINISHED'", order_by=["attributes.start_time DESC"], max_results=20):
        names = {f.path for f in client.list_artifacts(run.info.run_id, "checkpoints")}
        if "checkpoints/best.ckpt" in names:
            return run.info.run_id, _download(tracking_uri, run.info.run_id, "checkpoints/best.ckpt", cache_dir)
    return None


def resolve_tokenizer(reference: str | None, tracking_uri: str, output_dir: str = "outputs/stage1", cache_dir: str = "outputs/cache/models") -> tuple[str, str, str | None]:
    """(resolved reference, local checkpoint path, run id or None) for a tokenizer reference."""
    cache = Path(cache_dir)
    if reference is None:
        found = _newest_run_checkpoint(tracking_uri, cache)
        if found:
            return f"runs:/{found[0]}", found[1], found[0]
        local = sorted(Path(output_dir).glob("*/checkpoints/best.ckpt"), key=lambda p: p.stat().st_mtime)
        if local:
            return str(local[-1]), str(local[-1]), None
        raise ModelNotFound(
            f"no stage-1 model to use: no finished run with a checkpoint in MLflow experiment {STAGE1_EXPERIMENT!r} "
            f"at {tracking_uri} and no {output_dir}/*/checkpoints/best.ckpt; run `make train-stage1` first or name one with stage1=PATH|RUN_ID|models:/NAME@ALIAS"
        )
    if reference.startswith("models:/"):
        from mlflow.exceptions import MlflowException
        from mlflow.tracking import MlflowClient

        client = MlflowClient(tracking_uri)
        body = reference[len("models:/"):]
        try:
            if "@" in body:
                name, alias = body.split("@", 1)
                version = client.get_model_version_by_alias(name, alias)
            else:
                name, number = body.rsplit("/", 1)
                version = client.get_model_version(name, number)
        except MlflowException as e:
            raise ModelNotFound(f"{reference}: no such registered model version at {tracking_uri} ({e.message.splitlines()[0]}); `mmm models list` shows what exists") from None
        source = version.source
        run_id = version.run_id
        path = source.split(f"runs:/{run_id}/", 1)[-1] if source.startswith("runs:/") else None
        if path is None or run_id is None:
            raise ModelNotFound(f"{reference}: version {version.version} has source {source!r}, not a run artifact of a stage-1 checkpoint")
        if not path.endswith(".ckpt"):
            path = path.rstrip("/") + "/best.ckpt"
        return reference, _download(tracking_uri, run_id, path, cache), run_id
    run_id = reference[len("runs:/"):].strip("/") if reference.startswith("runs:/") else reference
    if _RUN_ID.match(run_id):
        return f"runs:/{run_id}", _download(tracking_uri, run_id, "checkpoints/best.ckpt", cache), run_id
    path = Path(reference)
    if not path.exists():
        raise ModelNotFound(f"{reference}: no such checkpoint file, MLflow run id or models:/ URI")
    return str(path), str(path), None


def load_tokenizer_checkpoint(path: str | Path) -> TokenizerModule:
    """A TokenizerModule in eval mode from a stage-1 checkpoint (weights_only load)."""
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    hp = ckpt.get("hyper_parameters") or {}
    if "model" not in hp or "feature_dim" not in hp:
        raise ValueError(f"{path}: not a stage-1 tokenizer checkpoint (no tokenizer hyper-parameters in it)")
    module = TokenizerModule(hp["feature_dim"], hp["model"], hp["optim"], hp["loss"])
    module.load_state_dict(ckpt["state_dict"])
    return module.eval()


def load_tokenizer(reference: str | None, tracking_uri: str, output_dir: str = "outputs/stage1") -> tuple[TokenizerModule, TokenizerSource]:
    resolved, checkpoint, run_id = resolve_tokenizer(reference, tracking_uri, output_dir)
    module = load_tokenizer_checkpoint(checkpoint)
    identity = tensors_fingerprint(module.state_dict())
    return module, TokenizerSource(resolved, checkpoint, run_id, identity)

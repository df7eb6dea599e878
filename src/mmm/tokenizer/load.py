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

from dataclasses import dataclass
from pathlib import Path

import torch

from mmm.fingerprint import tensors_fingerprint
from mmm.resolve import ModelNotFound, resolve_checkpoint
from mmm.tokenizer.module import TokenizerModule

STAGE1_EXPERIMENT = "mmm-stage1"

__all__ = ["ModelNotFound", "TokenizerSource", "load_tokenizer", "load_tokenizer_checkpoint", "resolve_tokenizer"]


@dataclass
class TokenizerSource:
    reference: str  # what was asked for, resolved ("runs:/...", a path, "models:/...")
    checkpoint: str  # local file
    run_id: str | None
    identity: str  # fingerprint of the tokenizer's weights and normalization


def resolve_tokenizer(reference: str | None, tracking_uri: str, output_dir: str = "outputs/stage1", cache_dir: str = "outputs/cache/models",
                      experiment: str = STAGE1_EXPERIMENT) -> tuple[str, str, str | None]:
    """(resolved reference, local checkpoint path, run id or None) for a tokenizer reference
    (None: the newest run of `experiment`, mmm-stage1-parts for the part-aware tokenizer)."""
    hint = "make train-stage1-parts" if experiment.endswith("-parts") else "make train-stage1"
    return resolve_checkpoint(reference, tracking_uri, experiment, output_dir, "stage-1 model", hint, "stage1", cache_dir)


def load_tokenizer_checkpoint(path: str | Path) -> TokenizerModule:
    """A TokenizerModule in eval mode from a stage-1 checkpoint (weights_only load); its
    hyper-parameters say whether the tokenizer is plain or part-aware (`model.part_aware`)."""
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    hp = ckpt.get("hyper_parameters") or {}
    if "model" not in hp or "feature_dim" not in hp:
        raise ValueError(f"{path}: not a stage-1 tokenizer checkpoint (no tokenizer hyper-parameters in it)")
    module = TokenizerModule(hp["feature_dim"], hp["model"], hp["optim"], hp["loss"])
    module.load_state_dict(ckpt["state_dict"])
    return module.eval()


def load_tokenizer(reference: str | None, tracking_uri: str, output_dir: str = "outputs/stage1",
                   experiment: str = STAGE1_EXPERIMENT) -> tuple[TokenizerModule, TokenizerSource]:
    resolved, checkpoint, run_id = resolve_tokenizer(reference, tracking_uri, output_dir, experiment=experiment)
    module = load_tokenizer_checkpoint(checkpoint)
    identity = tensors_fingerprint(module.state_dict())
    return module, TokenizerSource(resolved, checkpoint, run_id, identity)

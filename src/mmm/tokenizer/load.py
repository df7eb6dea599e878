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

from mmm.checkpoints import CheckpointError, load_checkpoint, load_state
from mmm.fingerprint import tensors_fingerprint
from mmm.kinds import STAGE1, STAGE1_PARTS
from mmm.resolve import ModelNotFound, resolve_model
from mmm.tokenizer.module import TokenizerModule

STAGE1_EXPERIMENT = STAGE1.experiment

__all__ = [
    "ModelNotFound",
    "TokenizerSource",
    "load_tokenizer",
    "load_tokenizer_checkpoint",
    "resolve_tokenizer",
]


@dataclass
class TokenizerSource:
    reference: str  # what was asked for, resolved ("runs:/...", a path, "models:/...")
    checkpoint: str  # local file
    run_id: str | None
    identity: str  # fingerprint of the tokenizer's weights and normalization


def resolve_tokenizer(
    reference: str | None,
    tracking_uri: str,
    output_dir: str = STAGE1.output_dir,
    cache_dir: str = "outputs/cache/models",
    experiment: str = STAGE1_EXPERIMENT,
) -> tuple[str, str, str | None]:
    """(resolved reference, local checkpoint path, run id or None) for a tokenizer reference
    (None: the newest run of `experiment`, mmm-stage1-parts for the part-aware tokenizer)."""
    kind = STAGE1_PARTS if experiment == STAGE1_PARTS.experiment else STAGE1
    return resolve_model(reference, tracking_uri, kind, "stage1", output_dir, cache_dir, experiment)


def load_tokenizer_checkpoint(path: str | Path, expected_fingerprint: str | None = None) -> TokenizerModule:
    """A TokenizerModule in eval mode from a stage-1 checkpoint (weights_only load); its
    hyper-parameters say whether the tokenizer is plain or part-aware (`model.part_aware`).
    Anything but an intact stage-1 checkpoint (weights with the fingerprint recorded at save time,
    and `expected_fingerprint` when given) is a CheckpointError naming the file."""
    ckpt = load_checkpoint(path, "stage1", expected_fingerprint)
    hp = ckpt["hyper_parameters"]
    try:
        module = TokenizerModule(
            hp["feature_dim"],
            hp["model"],
            hp.get("optim") or {},
            hp.get("loss") or {},
            refine=hp.get("refine"),
            encode=hp.get("encode"),  # absent (before the code search): the default search
        )
    except (TypeError, ValueError, KeyError) as e:
        raise CheckpointError(
            f"{path}: its stage-1 hyper-parameters do not describe a tokenizer ({e}); use the checkpoint as "
            "training wrote it"
        ) from None
    load_state(module, ckpt["state_dict"], path, "stage1")
    return module.eval()


def load_tokenizer(
    reference: str | None,
    tracking_uri: str,
    output_dir: str = STAGE1.output_dir,
    experiment: str = STAGE1_EXPERIMENT,
) -> tuple[TokenizerModule, TokenizerSource]:
    resolved, checkpoint, run_id = resolve_tokenizer(
        reference, tracking_uri, output_dir, experiment=experiment
    )
    module = load_tokenizer_checkpoint(checkpoint)
    identity = tensors_fingerprint(module.state_dict())
    return module, TokenizerSource(resolved, checkpoint, run_id, identity)

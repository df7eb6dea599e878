"""`mmm import released`: the authors' released checkpoints as this package's models, registered.

    mmm import released --vq VQ/net_last.pth --transformer T2M/net_last.pth \
        --stats checkpoints/t2m/VQVAEV3_CB1024_CMT_H1024_NRES3/meta --clip ViT-B-32.pt

reads the released stage-1 (`{"net": ...}`) and stage-2 (`{"trans": ...}`) files with
`torch.load(weights_only=True)`, maps every key (keys.py), and writes this package's checkpoints:
the tokenizer with the normalization statistics the release trained with, the transformer as the
`released` variant with its stage-1 identity and the CLIP text encoder as released (float16, all
77 word positions). Each is logged as a run of the MLflow experiment `mmm-import` and registered
(`mmm-tokenizer`; `mmm-text2motion` as the self-contained bundle), tagged `mmm.imported=released`
with the source files' sha256, under an alias (`released` by default), so that generation,
editing, evaluation, promotion and `mlflow models serve` take them as they take trained models.
Importing the same files again reuses the registered versions.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import mlflow
import numpy as np
import torch
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from mmm.atomic import atomic_write, sha256_file
from mmm.data.normalization import read_stats_folder
from mmm.fingerprint import tensors_fingerprint
from mmm.optim import OptimConfig
from mmm.registry.bundle import log_bundle
from mmm.registry.versions import TEXT2MOTION, TOKENIZER, register_version, version_tags
from mmm.released.keys import (
    ReleasedKeyError,
    tokenizer_from_released,
    tokenizer_to_released,
    transformer_from_released,
    transformer_to_released,
)
from mmm.resolve import log_artifact_with_digest
from mmm.text import build_text_encoder
from mmm.text.clip import find_vocab
from mmm.tokenizer.configs import TokenizerLossConfig
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.search import CodeSearchConfig
from mmm.tracking import artifact_location, prepare_experiment, resolve_tracking_uri
from mmm.transformer.configs import CorruptionConfig
from mmm.transformer.module import MaskedTransformerModule

log = logging.getLogger(__name__)

EXPERIMENT = "mmm-import"
IMPORTED_TAG = "mmm.imported"
UPPER_BODY_REFUSAL = (
    "the released upper-body pair cannot be mapped onto this package's part-aware model: its two-part "
    "tokenizer moves the "
    "upper-body joint heights to the root (subtracting the root height) and renormalizes them with "
    "statistics of its own "
    "before encoding, and undoes that after decoding; this package's part-aware tokenizer has no such step, "
    "so the "
    "released codes would decode into wrong upper bodies (no training script was released for it either, so "
    "its "
    "settings cannot be reproduced). Train the part-aware model here instead: make train-stage1-parts "
    "train-stage2-parts"
)


class ImportRefused(ValueError):
    """A file this importer will not take, with the reason."""


@dataclass
class ImportedModels:
    tokenizer_checkpoint: str
    transformer_checkpoint: str | None
    tokenizer_version: str | None = None
    text2motion_version: str | None = None
    alias: str | None = None
    reused: bool = False


def read_released(path: str | Path, key: str, what: str) -> dict[str, torch.Tensor]:
    """The state dict stored under `key` in a released file, loaded without running any code."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file; give the released {what} checkpoint (net_last.pth)")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # an empty or truncated file, another format, a pickle that needs code
        reason = (str(e).splitlines() or ["no message"])[0][:200]
        raise ImportRefused(
            f"{path}: cannot be read as a released {what} checkpoint with weights_only=True "
            f"({type(e).__name__}: {reason}); download it again"
        ) from None
    if not isinstance(obj, dict) or not isinstance(obj.get(key), dict):
        found = sorted(map(str, obj))[:6] if isinstance(obj, dict) else type(obj).__name__
        raise ImportRefused(
            f"{path}: a released {what} checkpoint is {{'{key}': state_dict}}, this holds {found}"
        )
    state = obj[key]
    bad = [k for k, v in state.items() if not isinstance(k, str) or not torch.is_tensor(v)]
    if bad:
        raise ImportRefused(
            f"{path}: entries that are not parameter names with tensors: {', '.join(map(str, bad[:5]))}"
        )
    if any("_upper" in k or "_lower" in k for k in state):
        raise ImportRefused(f"{path}: {UPPER_BODY_REFUSAL}")
    return state


def read_stats(folder: str | Path, feature_dim: int) -> tuple[np.ndarray, np.ndarray, str]:
    """(mean, std, sha256 of both) from mean.npy/std.npy (the T2M evaluator's meta folder, which
    the release normalizes with) or Mean.npy/Std.npy in `folder`."""
    if not Path(folder).is_dir():
        raise FileNotFoundError(
            f"--stats {folder}: no such folder; give the folder with the mean.npy/std.npy the release was "
            "trained with (the T2M evaluator's checkpoints/t2m/VQVAEV3_CB1024_CMT_H1024_NRES3/meta)"
        )
    mean, std = read_stats_folder(folder, feature_dim)
    return mean, std, hashlib.sha256(mean.tobytes() + std.tobytes()).hexdigest()


def _save_atomic(obj: dict, path: Path) -> None:
    with atomic_write(path) as fh:
        torch.save(obj, fh)


def build_tokenizer(net: dict[str, torch.Tensor], source: str, mean: np.ndarray, std: np.ndarray):
    """A TokenizerModule holding the released stage-1 weights and the statistics it normalizes with."""
    state, sizes = tokenizer_from_released(net, source)
    # The released tokenizer encodes to the nearest code; an imported one does too (encode.candidates 1).
    module = TokenizerModule(
        sizes.feature_dim,
        sizes.config(),
        OptimConfig(),
        TokenizerLossConfig(),
        mean,
        std,
        encode=CodeSearchConfig(candidates=1),
    )
    module.load_state_dict({**state, "mean": torch.as_tensor(mean), "std": torch.as_tensor(std)}, strict=True)
    return module.eval()


def build_transformer(
    trans: dict[str, torch.Tensor],
    source: str,
    tokenizer,
    stage1: dict,
    text_encoder,
    text: dict,
    heads: int | None,
):
    """A MaskedTransformerModule (variant released) holding the released stage-2 weights; the stage-1
    model embedded in the file must be `tokenizer`'s."""
    state, vq, sizes = transformer_from_released(trans, source)
    ours = tokenizer_to_released(tokenizer.state_dict(), tokenizer.model_cfg, tokenizer.tokenizer.feature_dim)
    differ = sorted(
        k
        for k in set(ours) | set(vq)
        if k not in vq or k not in ours or not torch.equal(vq[k].float(), ours[k].float())
    )
    if differ:
        raise ImportRefused(
            f"{source}: the stage-1 model inside it (trans_base.vqvae.*) is not the one given with --vq "
            f"(first differing entries: {', '.join(differ[:4])}); give the VQ-VAE this transformer was "
            "trained with"
        )
    if (sizes.sentence_dim, sizes.word_dim) != (text_encoder.sentence_dim, text_encoder.word_dim):
        raise ImportRefused(
            f"{source}: it reads {sizes.sentence_dim}-d sentence and {sizes.word_dim}-d word features, the "
            "text encoder "
            f"gives {text_encoder.sentence_dim}/{text_encoder.word_dim}"
        )
    heads = heads or max(1, sizes.embed_dim // 64)  # the release's heads are 64 wide (16 at E = 1024)
    if sizes.embed_dim % heads:
        raise ImportRefused(f"--heads {heads} does not divide the embedding width {sizes.embed_dim}")
    # The release's stage-2 recipe: AdamW (0.5, 0.9), lr 2e-4, x0.05 at 150k, no warm-up, no text dropout.
    optim = OptimConfig(
        lr=2e-4, betas=[0.5, 0.9], weight_decay=1e-6, warmup_steps=0, milestones=[150_000], gamma=0.05
    )
    codebook = tokenizer.tokenizer.codebook.detach().cpu()
    module = MaskedTransformerModule(
        codebook,
        sizes.config(heads),
        optim,
        CorruptionConfig(cond_drop=0.0),
        sizes.sentence_dim,
        sizes.word_dim,
        stage1,
        text,
    )
    module.load_state_dict({**state, "transformer.codebook": codebook}, strict=True)
    return module.eval()


def released_text_encoder(clip: str | Path, vocab: str | Path | None):
    """CLIP ViT-B/32 as the release computes it: float16, all 77 word positions."""
    options = {
        "weights": str(clip),
        "vocab": str(vocab) if vocab else None,
        "activation": "quick_gelu",
        "precision": "float16",
        "words": "all",
    }
    encoder = build_text_encoder("clip", **{k: v for k, v in options.items() if v is not None})
    vocab_path = str(vocab) if vocab else None
    if vocab_path is None:
        vocab_path = str(find_vocab())
    options["vocab"] = vocab_path
    return encoder, {"name": encoder.name, "identity": encoder.identity, **options}


def _existing(client, name: str, tags: dict[str, str]):
    """A version of `name` imported from exactly these files, or None."""
    try:
        versions = client.search_model_versions(f"name='{name}'")
    except MlflowException:
        return None
    for v in versions:
        if all(v.tags.get(k) == val for k, val in tags.items()):
            return v
    return None


def import_released(
    vq: str | Path,
    stats: str | Path,
    transformer: str | Path | None = None,
    clip: str | Path | None = None,
    clip_vocab: str | Path | None = None,
    alias: str = "released",
    heads: int | None = None,
    out_dir: str | Path = "outputs/imported",
    tracking_uri: str = "sqlite:///mlflow.db",
    artifact_root: str = "mlartifacts",
    register: bool = True,
) -> ImportedModels:
    """Import the released stage-1 (and stage-2) checkpoints; see the module docstring."""
    if alias == "champion":
        raise ImportRefused(
            "--alias champion: the champion alias moves only when `mmm promote` measures a model better than "
            "the "
            "current one; import under another alias, then promote: mmm promote text2motion candidate=RUN_ID"
        )
    if transformer is not None and clip is None:
        raise ImportRefused(
            "--transformer needs --clip PATH: the released transformer reads OpenAI CLIP ViT-B/32 features "
            "(OpenAI's ViT-B-32.pt, or open_clip's ViT-B-32 OpenAI weights)"
        )
    net = read_released(vq, "net", "stage-1 (VQ-VAE)")
    trans = read_released(transformer, "trans", "stage-2 (transformer)") if transformer is not None else None
    try:
        feature_dim = int(net["vqvae.encoder.model.0.weight"].shape[1])
    except KeyError:
        raise ImportRefused(
            f"{vq}: not a released stage-1 (VQ-VAE) checkpoint: missing vqvae.encoder.model.0.weight"
        ) from None
    mean, std, stats_sha = read_stats(stats, feature_dim)
    sources = {"source.vq.sha256": sha256_file(vq), "source.stats.sha256": stats_sha}
    # Everything is read, mapped and checked before anything is written.
    tokenizer = build_tokenizer(net, str(vq), mean, std)
    tokenizer_identity = tensors_fingerprint(tokenizer.state_dict())
    folder = Path(out_dir) / f"released-{sources['source.vq.sha256'][:12]}"
    tokenizer_path = folder / "tokenizer.ckpt"
    imported = {
        "from": "released",
        "vq": str(Path(vq).resolve()),
        "stats": str(Path(stats).resolve()),
        **sources,
    }
    module = None
    if trans is not None:
        sources.update(
            {"source.transformer.sha256": sha256_file(transformer), "source.clip.sha256": sha256_file(clip)}
        )
        encoder, text = released_text_encoder(clip, clip_vocab)
        stage1 = {
            "reference": str(tokenizer_path),
            "run_id": None,
            "identity": tokenizer_identity,
            "checkpoint": str(tokenizer_path.resolve()),
        }
        module = build_transformer(trans, str(transformer), tokenizer, stage1, encoder, text, heads)
    _save_atomic(
        {
            "state_dict": tokenizer.state_dict(),
            "hyper_parameters": dict(tokenizer.hparams),
            "imported": imported,
            "epoch": 0,
            "global_step": 0,
        },
        tokenizer_path,
    )
    result = ImportedModels(str(tokenizer_path), None, alias=alias if register else None)
    if module is not None:
        transformer_path = folder / f"transformer-{sources['source.transformer.sha256'][:12]}.ckpt"
        _save_atomic(
            {
                "state_dict": module.state_dict(),
                "hyper_parameters": dict(module.hparams),
                "imported": {**imported, "transformer": str(Path(transformer).resolve()), **sources},
                "epoch": 0,
                "global_step": 0,
            },
            transformer_path,
        )
        result.transformer_checkpoint = str(transformer_path)
    if register:
        _register(result, sources, tokenizer_identity, tracking_uri, artifact_root)
    return result


def _register(
    result: ImportedModels,
    sources: dict[str, str],
    tokenizer_identity: str,
    tracking_uri: str,
    artifact_root: str,
) -> None:
    """Log each checkpoint as a run of mmm-import, register it and set the alias (or reuse the
    versions an earlier import of the same files registered)."""
    uri = resolve_tracking_uri(tracking_uri)
    client = MlflowClient(uri)

    experiment_id = prepare_experiment(
        client, EXPERIMENT, artifact_location(uri, artifact_root)
    )  # another process creating it too is fine
    mlflow.set_tracking_uri(uri)
    base_tags = {IMPORTED_TAG: "released", **sources}

    def registered(name: str, keys: list[str], log, description: str) -> str:
        wanted = {IMPORTED_TAG: "released", **{k: sources[k] for k in keys}}
        version = _existing(client, name, wanted)
        if version is None:
            with mlflow.start_run(
                experiment_id=experiment_id, run_name=f"import-{name.removeprefix('mmm-')}"
            ) as run:
                mlflow.set_tags({**wanted, "mmm.stage": "import"})
                source = log(run.info.run_id)
            tags = version_tags({}, "", None, None, {**wanted, "tokenizer.identity": tokenizer_identity})
            version = register_version(client, name, source, run.info.run_id, tags, description)
        else:
            result.reused = True
        client.set_registered_model_alias(name, result.alias, version.version)
        return str(version.version)

    def log_tokenizer(run_id: str) -> str:
        with tempfile.TemporaryDirectory() as tmp:
            staged = Path(tmp) / "best.ckpt"
            shutil.copyfile(result.tokenizer_checkpoint, staged)
            log_artifact_with_digest(
                client, run_id, staged, "checkpoints"
            )  # its sha256 keys the download cache
        return f"runs:/{run_id}/checkpoints"

    result.tokenizer_version = registered(
        TOKENIZER,
        ["source.vq.sha256", "source.stats.sha256"],
        log_tokenizer,
        "the authors' released VQ-VAE, imported (mmm import released)",
    )
    if result.transformer_checkpoint:

        def log_text2motion(run_id: str) -> str:
            with tempfile.TemporaryDirectory() as tmp:
                staged = Path(tmp) / "best.ckpt"
                shutil.copyfile(result.transformer_checkpoint, staged)
                log_artifact_with_digest(client, run_id, staged, "checkpoints")
            return log_bundle(
                result.transformer_checkpoint, result.tokenizer_checkpoint, artifact_path="bundle"
            ).model_uri

        result.text2motion_version = registered(
            TEXT2MOTION,
            list(base_tags.keys() - {IMPORTED_TAG}),
            log_text2motion,
            "the authors' released transformer with its VQ-VAE and CLIP text encoder, imported",
        )


def export_released(tokenizer, transformer=None) -> tuple[dict, dict | None]:
    """({"net": ...}, {"trans": ...} or None) in the released file layout, from a TokenizerModule and
    a released-variant MaskedMotionTransformer (e.g. `TextToMotion.load(...)`'s)."""
    net = tokenizer_to_released(tokenizer.state_dict(), tokenizer.model_cfg, tokenizer.tokenizer.feature_dim)
    if transformer is None:
        return {"net": net}, None
    state = {f"transformer.{k}": v for k, v in transformer.state_dict().items()}
    try:
        trans = transformer_to_released(state, transformer.cfg, net)
    except ValueError as e:
        raise ImportRefused(f"cannot export this transformer in the released layout: {e}") from None
    return {"net": net}, {"trans": trans}


__all__ = [
    "ImportRefused",
    "ImportedModels",
    "ReleasedKeyError",
    "UPPER_BODY_REFUSAL",
    "export_released",
    "import_released",
]

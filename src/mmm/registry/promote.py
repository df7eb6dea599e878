"""`mmm promote tokenizer|text2motion|evaluator|upperbody [key=value ...]`: evaluate a candidate
run, register it as a new version, and move `champion` to it only when it wins (see versions.py).

Candidates default to the newest finished run of the kind's experiment. Metrics are measured here,
on the configured data (its fingerprint is recorded) with the champion evaluator (or the newest
one): tokenizer: reconstruction MPJPE and FID on the split; text2motion: the protocol (reduced
by conf/promote.yaml) and, on labelled data, prompt adherence (`adherence/*`: strict and
order-aware, per group; a criterion may name them); evaluator: its own test retrieval numbers
from training; upperbody (the part-aware model): upper-body editing adherence on labelled data
(no evaluator needed). The
version is tagged with the criteria's metrics (and their intervals) and described in markdown:
what it is, the criteria with its and the champion's values, the verdict and why, every measured
number, and links to the model's run and the previous champion.
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import asdict
from pathlib import Path

import mlflow
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig

from mmm.atomic import sha256_file
from mmm.config import to_object
from mmm.data.configs import DataConfig
from mmm.data.humanml3d import load_stats
from mmm.device import check_device
from mmm.evaluation.adherence import adherence_metrics, prompt_adherence
from mmm.evaluation.configs import EditingConfig
from mmm.evaluation.evaluators import load_evaluator
from mmm.evaluation.protocol import evaluate_text_to_motion
from mmm.evaluation.run import reconstruction_metrics
from mmm.evaluation.samples import render_samples
from mmm.evaluation.upper_body import upper_body_adherence
from mmm.fingerprint import dataset_fingerprint, tensors_fingerprint
from mmm.generation.model import TextToMotion
from mmm.kinds import PROMOTABLE
from mmm.registry.bundle import JudgeMismatch, log_bundle
from mmm.registry.configs import Criterion, PromoteConfig
from mmm.registry.versions import (
    CI_SUFFIX,
    EVALUATOR,
    TEXT2MOTION,
    TOKENIZER,
    UPPERBODY,
    WEIGHTS_SHA256,
    Decision,
    freeze_weights,
    promote_version,
    register_version,
    registered_before,
    retag_version,
    version_tags,
)
from mmm.resolve import ModelNotFound, download_artifact
from mmm.tokenizer.load import load_tokenizer_checkpoint
from mmm.tracking import store_for_reading

log = logging.getLogger(__name__)

# The registered models' own descriptions (each version's description says what that version is and why it
# has its alias).
MODEL_DESCRIPTIONS = {
    TOKENIZER: (
        "Stage-1 motion tokenizers (VQ-VAE), promoted on reconstruction (conf/promote.yaml "
        "`criteria.tokenizer`)."
    ),
    TEXT2MOTION: (
        "Text-to-motion bundles (tokenizer, transformer, normalization, text encoder), promoted on the "
        "evaluation protocol "
        "(conf/promote.yaml `criteria.text2motion`); `@champion` is what generation uses by default."
    ),
    EVALUATOR: (
        "Contrastive text-motion evaluators: the yardstick generators are promoted with (conf/promote.yaml "
        "`criteria.evaluator`)."
    ),
    UPPERBODY: (
        "Part-aware models for upper-body editing, promoted on editing adherence (conf/promote.yaml "
        "`criteria.upperbody`)."
    ),
}


def _length_rules(data: DataConfig) -> dict:
    return {
        "data.fps": data.fps,
        "data.min_length": data.min_length,
        "data.length_limit": data.length_limit,
        "data.on_invalid": data.on_invalid,
    }


def _newest_run(client, experiment: str) -> str:
    found = client.get_experiment_by_name(experiment)
    runs = (
        client.search_runs(
            [found.experiment_id],
            "attributes.status = 'FINISHED'",
            order_by=["attributes.start_time DESC"],
            max_results=20,
        )
        if found
        else []
    )
    for run in runs:
        if any(
            f.path == "checkpoints/best.ckpt" for f in client.list_artifacts(run.info.run_id, "checkpoints")
        ):
            return run.info.run_id
    raise ModelNotFound(
        f"no finished run with a checkpoint in MLflow experiment {experiment!r}: train one first"
    )


def _evaluator(cfg: PromoteConfig, tracking_uri: str, required: bool):
    """The evaluator the metrics are measured with: the configured one, the champion, or the newest."""
    reference = cfg.evaluator
    if reference is None:
        try:
            MlflowClient(tracking_uri).get_model_version_by_alias(EVALUATOR, "champion")
            reference = f"models:/{EVALUATOR}@champion"
        except MlflowException:
            reference = None
    try:
        return load_evaluator(reference, tracking_uri, cfg.device)
    except ModelNotFound:
        if required:
            raise
        log.warning(
            "no evaluator found: tokenizer promotion measures MPJPE only (train one with `make "
            "train-evaluator`)"
        )
        return None


def _decision_metrics(
    metrics: dict[str, float], intervals: dict[str, float], criteria: list[Criterion]
) -> dict[str, float]:
    """The metrics a version is tagged with: the criteria's, each with its interval where it has one."""
    chosen = {}
    for c in criteria:
        if c.metric in metrics:
            chosen[c.metric] = metrics[c.metric]
            if c.metric in intervals:
                chosen[c.metric + CI_SUFFIX] = intervals[c.metric]
        else:
            log.warning(
                "criterion %s was not measured (measured: %s): the candidate cannot beat a champion on it",
                c.metric,
                ", ".join(sorted(metrics)) or "nothing",
            )
    return chosen


def _measurements(metrics: dict[str, float], intervals: dict[str, float]) -> str:
    """Every measured number, for the version's description (its tags keep only the criteria's)."""

    def value(k):
        return f"{metrics[k]:.4g}" + (f" ± {intervals[k]:.2g}" if k in intervals else "")

    return "; all measured: " + ", ".join(f"`{k}` {value(k)}" for k in sorted(metrics)) if metrics else ""


def promote(kind: str, cfg_node: DictConfig) -> Decision:
    if kind not in PROMOTABLE:
        raise ValueError(f"unknown model kind {kind!r}; choose {', '.join(PROMOTABLE)}")
    cfg: PromoteConfig = to_object(cfg_node)
    check_device(cfg.device)
    uri = store_for_reading(cfg.logger.tracking_uri)  # a candidate is read from a store that exists
    client = MlflowClient(uri)
    run_id = cfg.candidate or _newest_run(client, PROMOTABLE[kind].experiment)
    try:
        run = client.get_run(run_id)
    except MlflowException as e:
        raise ModelNotFound(
            f"candidate={run_id}: no such run in the tracking store {uri} ({e.message.splitlines()[0]}); "
            f"name a run of experiment {PROMOTABLE[kind].experiment!r}, or leave candidate out for its newest"
        ) from None
    criteria = getattr(cfg.criteria, kind)
    config_hash = run.data.tags.get("config.hash")
    root = Path(cfg.data.root)
    intervals: dict[str, float] = {}
    if kind == "evaluator":
        metrics = {k: v for k, v in run.data.metrics.items() if k.startswith("test/")}
        existing = registered_before(client, EVALUATOR, run_id, {})
        fingerprint = run.data.tags.get("data.fingerprint", "")
        params = run.data.params
        protocol = {
            "split": "test",
            "measured_by": "training run",
            **{k: params.get(k) for k in sorted(params) if k.startswith("retrieval.")},
            "data.min_length": params.get("data.min_length"),
            "data.length_limit": params.get("data.length_limit"),
            "data.max_length": params.get("data.max_length"),
        }
        tags = version_tags(
            _decision_metrics(metrics, intervals, criteria),
            fingerprint,
            None,
            config_hash,
            {"text_encoder": run.data.tags.get("text_encoder", "")},
            protocol=protocol,
        )
        about = (
            "The package's own contrastive text-motion evaluator (motion encoder and text head over the "
            "frozen sentence embeddings of "
            f"`{tags['text_encoder'] or '?'}`): the yardstick generators are promoted with. Source: a copy "
            "of its best checkpoint kept "
            "in its training run under `registered/` (a resumed run never rewrites it)."
        )
        if existing is not None:
            version = retag_version(client, EVALUATOR, existing, tags)
            if version.description and not version.description.startswith("### "):
                about += f" Registered by its training: {version.description}"
        else:
            local = download_artifact(uri, run_id, "checkpoints/best.ckpt", "outputs/cache/models")
            source, digest = freeze_weights(client, run_id, local, EVALUATOR)
            version = register_version(
                client,
                EVALUATOR,
                source,
                run_id,
                {**tags, WEIGHTS_SHA256: digest},
                about,
                MODEL_DESCRIPTIONS[EVALUATOR],
            )
        measured = (
            f"retrieval on the {run.data.tags.get('data.name', 'data')} test split, by its training "
            f"run{_measurements(metrics, intervals)}"
        )
        return promote_version(
            client,
            EVALUATOR,
            version.version,
            criteria,
            needs_evaluator=False,
            about=about,
            measured=measured,
        )
    fingerprint = dataset_fingerprint(root)
    checkpoint = download_artifact(uri, run_id, "checkpoints/best.ckpt", "outputs/cache/models")
    if kind == "tokenizer":
        tokenizer = load_tokenizer_checkpoint(checkpoint).to(cfg.device)
        evaluator = _evaluator(cfg, uri, required=any(c.metric == "recon/fid" for c in criteria))
        clips, _ = cfg.data.clips(cfg.split, root)
        recon = reconstruction_metrics(tokenizer, evaluator, clips)
        metrics = {f"recon/{k}": v for k, v in recon.items() if k not in ("clips", "encoding")}
        metrics.update({k: v for k, v in run.data.metrics.items() if k.startswith("val/")})
        identity = tensors_fingerprint(tokenizer.state_dict())
        needs_fid = any(
            c.metric == "recon/fid" for c in criteria
        )  # MPJPE needs no evaluator: then which one was around does not matter
        protocol = {
            "split": cfg.split,
            "reconstruction": "whole clips",
            "data.min_length": cfg.data.min_length,
            "data.on_invalid": cfg.data.on_invalid,
            "evaluator": getattr(evaluator, "identity", None) if needs_fid else "not used",
        }
        tags = version_tags(
            _decision_metrics(metrics, intervals, criteria),
            fingerprint,
            getattr(evaluator, "identity", None),
            config_hash,
            {"tokenizer.identity": identity},
            protocol=protocol,
        )
        about = (
            "Stage-1 motion tokenizer (VQ-VAE: motion features to codes and back, with its feature "
            f"normalization), weights `{identity}`. "
            "Source: a copy of its best checkpoint kept in its training run under `registered/` (a resumed "
            "run never rewrites it)."
        )
        measured = (
            f"reconstruction of the {cfg.split} split ({recon['clips']} clips) by `mmm promote`"
            + (f", FID with evaluator `{evaluator.identity}`" if evaluator is not None else "")
            + "; `val/*` from the training run"
            + _measurements(metrics, intervals)
        )
        source, digest = freeze_weights(client, run_id, checkpoint, TOKENIZER)
        tags[WEIGHTS_SHA256] = digest
        existing = registered_before(client, TOKENIZER, run_id, {WEIGHTS_SHA256: digest})
        version = (
            retag_version(client, TOKENIZER, existing, tags)
            if existing is not None
            else register_version(
                client, TOKENIZER, source, run_id, tags, about, MODEL_DESCRIPTIONS[TOKENIZER]
            )
        )
        return promote_version(
            client,
            TOKENIZER,
            version.version,
            criteria,
            needs_evaluator=any(c.metric == "recon/fid" for c in criteria),
            about=about,
            measured=measured,
        )
    # text2motion and upperbody: measure, bundle, register.

    # The stage-1 file the checkpoint records is followed only inside outputs/, else its MLflow run
    # is used (TextToMotion.from_files); the bundle carries the file that was used and checked.
    model = TextToMotion.from_files(checkpoint, None, cfg.device, tracking_uri=uri)
    tokenizer_checkpoint = model.identity["stage1_checkpoint"]
    extra = {
        "stage1.identity": model.identity["stage1"]["identity"],
        "text_encoder": model.identity["text_encoder"],
    }
    judge = None  # the evaluator checkpoint the bundle carries for best of N (`candidates`)
    if kind == "upperbody":
        if not model.part_aware:
            raise ValueError(
                f"run {run_id} is a whole-body model; `promote upperbody` takes part-aware runs "
                "(mmm-stage2-parts)"
            )
        check = cfg.upper_body
        protocol = {
            "split": cfg.split,
            "upper_body.max_sources": check.max_sources,
            "upper_body.lower_mask": check.lower_mask,
            "upper_body.seed": check.seed,
            "labels": (root / "labels").is_dir(),
            **_length_rules(cfg.data),
        }
        if (root / "labels").is_dir():
            result = upper_body_adherence(
                model, root, cfg.split, check.max_sources, check.lower_mask, check.seed
            )
            metrics = {f"upper_body/{k}": v for k, v in result.items() if isinstance(v, float)}
            extra["upper_body.edits"] = result["edits"]
            measured = (
                f"upper-body editing adherence by `mmm promote` on the {cfg.split} split's labels: "
                f"{result['edits']} edits of "
                f"{result['sources']} walking/squatting clips, lower-body mask {check.lower_mask}, checked "
                "by the synthetic action checker"
            )
        else:  # no action labels to check edits against: only the run's validation numbers
            log.warning(
                "%s has no labels/: upper-body adherence not measured; criteria on upper_body/* cannot be "
                "met",
                root,
            )
            metrics = {}
            measured = f"not measured: {root} has no labels/ to check edits against"
        evaluator_identity, name, description = (
            None,
            UPPERBODY,
            "part-aware model for upper-body editing: tokenizer (lower/upper), transformer, text encoder",
        )
    else:
        if model.part_aware:
            raise ValueError(
                f"run {run_id} is a part-aware model (it edits upper bodies); promote it with `mmm promote "
                f"upperbody candidate={run_id}`"
            )

        evaluator = _evaluator(cfg, uri, required=True)
        if hasattr(evaluator, "sentence_embeddings"):  # the package's own, not the standard T2M one
            judge = evaluator.info.get("path")
        else:
            log.warning(
                "the bundle carries no best-of-N judge: the evaluator %s reads tagged captions, not text",
                evaluator.identity,
            )
        items, _ = cfg.data.items(cfg.split, root)
        mean, std = load_stats(root, cfg.data.feature_dim)
        result = evaluate_text_to_motion(model, evaluator, items, mean, std, cfg.protocol, progress=False)
        metrics, intervals = {}, {}
        for which in ("generated", "real"):
            for m, (value, ci) in result[which].items():
                metrics[f"{which}/{m}"], intervals[f"{which}/{m}"] = value, ci
        adherence = None
        if cfg.adherence and (root / "labels").is_dir():  # labelled data: what the captions ask is checkable
            adherence = prompt_adherence(
                model,
                root,
                items,
                cfg.protocol.sampling,
                cfg.protocol.seed,
                max_items=cfg.adherence_max_items,
            )
            metrics.update(adherence_metrics(adherence))
        rendered = _log_samples(client, run_id, model, items, root, cfg)
        evaluator_identity, name, description = (
            evaluator.identity,
            TEXT2MOTION,
            "text-to-motion bundle: tokenizer, transformer, normalization, text encoder",
        )
        p = cfg.protocol
        # Everything the numbers depend on besides the model and the data fingerprint: the split, the
        # protocol (replications, batches,
        # seed, the retrieval batch size, diversity and multimodality sizes, sampling), the length rules, the
        # crop and the evaluator.
        protocol = {
            "split": cfg.split,
            "evaluator": evaluator.identity,
            "model.max_frames": model.max_frames,
            "model.unit": model.unit,
            **{f"protocol.{k}": v for k, v in asdict(p).items()},
            **_length_rules(cfg.data),
        }
        batches = "all the split's batches" if p.max_batches is None else f"at most {p.max_batches} batches"
        measured = (
            f"the text-to-motion protocol on the {cfg.split} split by `mmm promote` with evaluator "
            f"`{evaluator.identity}`: {p.replications} "
            f"replications over {batches} of {p.batch_size}"
        )
        if adherence is not None:
            measured += f"; prompt adherence (`adherence/*`) of {adherence['count']} labelled captions"
        if rendered:
            measured += (
                f"; {cfg.split} captions beside their real motions: `promotion/samples.gif` of its run"
            )
    metrics.update({k: v for k, v in run.data.metrics.items() if k.startswith("val/")})
    # The bundle holds copies of both checkpoints (logged with the model); their digests say which files they
    # are. The same weights promoted again keep their version and bundle, measured anew.
    weights = {
        "weights.transformer.sha256": sha256_file(checkpoint),
        "weights.tokenizer.sha256": sha256_file(tokenizer_checkpoint),
    }
    existing = registered_before(client, name, run_id, weights)
    extra.update(weights)
    if existing is None:
        info = _log_bundle(uri, run_id, checkpoint, tokenizer_checkpoint, judge)
        bundle_uri = info.model_uri
        # the evaluator the bundle's `candidates` param picks with ("" when it carries none)
        extra["judge.identity"] = ((info.metadata or {}).get("mmm") or {}).get("judge") or ""
    else:
        bundle_uri = existing.source
        extra["judge.identity"] = existing.tags.get("judge.identity", "")
    tags = version_tags(
        _decision_metrics(metrics, intervals, criteria),
        fingerprint,
        evaluator_identity,
        config_hash,
        extra,
        protocol=protocol,
    )
    about = (
        f"{description[0].upper()}{description[1:]}. An MLflow pyfunc model (`{bundle_uri}`, logged in "
        "the candidate's run as "
        f"`bundle`); stage-1 weights `{extra['stage1.identity']}`, text encoder `{extra['text_encoder']}`."
    )
    version = (
        retag_version(client, name, existing, tags)
        if existing is not None
        else register_version(client, name, bundle_uri, run_id, tags, about, MODEL_DESCRIPTIONS[name])
    )
    return promote_version(
        client,
        name,
        version.version,
        criteria,
        needs_evaluator=kind == "text2motion",
        about=about,
        measured=measured + _measurements(metrics, intervals),
    )


def _log_samples(client, run_id: str, model, items, root: Path, cfg: PromoteConfig) -> bool:
    """`cfg.samples` captions of the split, each real motion above the candidate's, logged to the
    candidate's run as promotion/samples.gif and .png: the motions behind the numbers, to look at
    before an alias moves. Whether anything was rendered."""
    with tempfile.TemporaryDirectory(prefix="mmm-promote-samples-") as tmp:
        files = render_samples(
            model,
            "text2motion",
            items,
            root,
            Path(tmp),
            cfg.samples,
            EditingConfig(),
            cfg.protocol.sampling,
            cfg.protocol.seed,
        )
        for path in files:
            client.log_artifact(run_id, str(path), "promotion")
    return bool(files)


def _log_bundle(uri: str, run_id: str, checkpoint: str, tokenizer_checkpoint: str, judge: str | None):
    """The bundle logged into the candidate's own run, whose status and end time are then put back:
    its duration in the dashboard stays the training's, not training until promotion. It carries
    `judge` (best of N) where that evaluator can read the model's motions and captions."""
    mlflow.set_tracking_uri(uri)
    before = mlflow.MlflowClient(uri).get_run(run_id).info
    try:
        with mlflow.start_run(run_id=run_id):
            try:
                return log_bundle(
                    checkpoint, tokenizer_checkpoint, artifact_path="bundle", judge_checkpoint=judge
                )
            except JudgeMismatch as e:  # checked before anything is logged
                log.warning("the bundle carries no best-of-N judge: %s", e)
                return log_bundle(checkpoint, tokenizer_checkpoint, artifact_path="bundle")
    finally:
        if before.end_time:
            mlflow.MlflowClient(uri).set_terminated(run_id, before.status, end_time=before.end_time)

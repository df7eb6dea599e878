"""The `mmm` command: data, conversion, rendering (training, generation and promotion join as they land).

Every subcommand exits 0 on success and 2 with a one-paragraph error (file, value, fix) on bad input.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("mmm")


class CLIError(Exception):
    pass


def _load_npy(path: str) -> np.ndarray:
    """A motion .npy (numbers only, never unpickled); DataError naming the file otherwise."""
    from mmm.data.arrays import load_array

    return load_array(path, "motion (.npy of features or joints)", "give a .npy of features (T, 263) or joints (T, 22, 3) written with numpy.save")


def _save_npy(path: str, array: np.ndarray) -> None:
    from mmm.data.humanml3d import save_array_atomic

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_array_atomic(out, array)
    print(f"wrote {out} {tuple(array.shape)}")


def cmd_convert(args: argparse.Namespace) -> None:
    from mmm.motion.features import joints_to_features, recover_from_ric
    from mmm.motion.skeleton import skeleton_for

    arr = _load_npy(args.input)
    if not np.isfinite(arr).all():
        raise CLIError(f"{args.input}: contains NaN/Inf values; fix the motion first")
    if args.direction == "joints-to-features":
        if arr.ndim != 3 or arr.shape[1:] not in ((22, 3), (21, 3)) or arr.shape[0] < 2:
            raise CLIError(f"{args.input}: shape {arr.shape}, expected joints (T, 22, 3) or (T, 21, 3) with T >= 2")
        out = joints_to_features(arr.astype(np.float32), skeleton_for(arr.shape[1]), retarget=not args.no_retarget)
    else:
        if arr.ndim != 2 or arr.shape[1] not in (263, 251) or arr.shape[0] < 1:
            raise CLIError(f"{args.input}: shape {arr.shape}, expected features (T, 263) or (T, 251)")
        out = recover_from_ric(arr.astype(np.float32))
    _save_npy(args.output, out.astype(np.float32))


def cmd_data_synth(args: argparse.Namespace) -> None:
    from mmm.data.synthetic.generate import generate_dataset
    from mmm.generation.sampler import SamplingValueError, check_seed

    try:
        check_seed(args.seed)
    except SamplingValueError as e:
        raise _option_error(e) from None
    summary = generate_dataset(args.out, num_clips=args.num_clips, seed=args.seed, overwrite=args.overwrite)
    print(summary)


def cmd_data_stats(args: argparse.Namespace) -> None:
    from mmm.data.arrays import load_array
    from mmm.data.humanml3d import compute_stats, save_array_atomic
    from mmm.data.normalization import evaluator_style_std
    from mmm.motion.features import FeatureLayout
    from mmm.motion.skeleton import SKELETONS

    root = Path(args.root)
    num_joints = SKELETONS[args.skeleton].num_joints
    mean, std, report = compute_stats(root, num_joints)
    print(f"{root}: statistics over {report.kept_clips} files")
    if report.skipped:
        print(report.summary())
    layout = FeatureLayout(num_joints)
    names = ("root yaw vel", "root xz vel", "root height", "positions", "rotations", "velocities", "contacts")
    if args.evaluator_style:
        scaled = evaluator_style_std(std, num_joints, args.feat_bias)
        print(f"evaluator-style: the root and foot-contact Std divided by {args.feat_bias:g} (what the released MMM normalizes with)")
        print(f"{'group':14s} {'mean(avg)':>10s} {'std':>10s} {'scaled std':>10s}")
        for name, sl in zip(names, layout.groups()):
            print(f"{name:14s} {mean[sl].mean():10.4f} {std[sl][0]:10.4f} {scaled[sl][0]:10.4f}")
        if args.write:
            folder = root / "evaluator_style"
            folder.mkdir(exist_ok=True)
            save_array_atomic(folder / "mean.npy", mean)
            save_array_atomic(folder / "std.npy", scaled)
            print(f"wrote {folder / 'mean.npy'} and {folder / 'std.npy'} (stage 1: normalization.statistics=files normalization.dir={folder})")
        return
    have = (root / "Mean.npy").exists() and (root / "Std.npy").exists()
    fix = f"delete it and write it again with `mmm data stats {root} --write`"
    old_mean = load_array(root / "Mean.npy", "saved Mean", fix) if have else None
    old_std = load_array(root / "Std.npy", "saved Std", fix) if have else None
    print(f"{'group':14s} {'mean(avg)':>10s} {'std':>10s}" + (f" {'saved std':>10s} {'max|dmean|':>10s}" if have else ""))
    for name, sl in zip(names, layout.groups()):
        row = f"{name:14s} {mean[sl].mean():10.4f} {std[sl][0]:10.4f}"
        if have:
            row += f" {old_std[sl][0]:10.4f} {np.abs(old_mean[sl] - mean[sl]).max():10.2e}"
        print(row)
    if args.write:
        save_array_atomic(root / "Mean.npy", mean)
        save_array_atomic(root / "Std.npy", std)
        print(f"wrote {root / 'Mean.npy'} and {root / 'Std.npy'}")


def cmd_data_check(args: argparse.Namespace) -> None:
    from mmm.data.humanml3d import check_mirror_splits, load_items, load_stats
    from mmm.motion.skeleton import SKELETONS

    sk = SKELETONS[args.skeleton]
    min_length = args.min_length or (24 if sk.name == "kit" else 40)
    root = Path(args.root)
    load_stats(root, sk.feature_dim)
    for split in ("train", "val", "test"):
        _, report = load_items(root, split, feature_dim=sk.feature_dim, fps=sk.fps, min_length=min_length, on_invalid=args.on_invalid)
        print(f"{split}: {report.summary()}")
    leaks = check_mirror_splits(root)
    print(f"mirrored ids in a different split from their original: {len(leaks)}" + (f" (e.g. {', '.join(leaks[:5])})" if leaks else ""))


def cmd_data_preview(args: argparse.Namespace) -> None:
    from mmm.data.preview import preview_dataset

    if args.count < 1:
        raise CLIError(f"--count {args.count} is not allowed: 1 or more clips to render")
    for path in preview_dataset(args.root, args.out, count=args.count, split=args.split):
        print(f"wrote {path}")


def cmd_render(args: argparse.Namespace) -> None:
    from mmm.render import render_files

    if args.fps is not None and not (math.isfinite(args.fps) and 0 < args.fps <= 1000):
        raise CLIError(f"--fps {args.fps} is not allowed: frames per second, more than 0 and at most 1000")
    for path in render_files(args.inputs, args.out, captions=args.caption or None, fps=args.fps):
        print(f"wrote {path}")


def cmd_train(args: argparse.Namespace) -> None:
    if args.stage in ("stage1", "stage1-parts"):
        from mmm.training.stage1 import load_stage1_config, train_stage1

        result = train_stage1(load_stage1_config(args.overrides, parts=args.stage.endswith("parts")), resume=args.resume)
    elif args.stage == "length":
        if args.resume:
            raise CLIError("--resume is not supported for the length estimator (it trains in seconds)")
        from mmm.training.length import load_length_config, train_length

        result = train_length(load_length_config(args.overrides))
    elif args.stage == "evaluator":
        if args.resume:
            raise CLIError("--resume is not supported for the evaluator (it trains in a few minutes)")
        from mmm.training.evaluator import load_evaluator_config, train_evaluator

        result = train_evaluator(load_evaluator_config(args.overrides))
    else:
        from mmm.training.stage2 import load_stage2_config, train_stage2

        result = train_stage2(load_stage2_config(args.overrides, parts=args.stage.endswith("parts")), resume=args.resume)
    if result.run_id is None and not result.best_checkpoint:
        return  # a non-zero rank of a distributed run
    print(f"MLflow run: {result.run_id}")
    print(f"checkpoints: best {result.best_checkpoint}, last {result.last_checkpoint}")
    shown = {k: v for k, v in sorted(result.metrics.items()) if k.startswith("val/")}
    print("validation: " + ", ".join(f"{k}={v:.4g}" for k, v in shown.items()))
    if getattr(result, "model_version", None):
        print("test: " + ", ".join(f"{k}={v:.4g}" for k, v in sorted(result.metrics.items()) if k.startswith("test/r_precision") or k == "test/matching_distance"))
        print(f"registered: models:/{result.registered_model}/{result.model_version}")


def cmd_tokenize(args: argparse.Namespace) -> None:
    from mmm.training.stage2 import load_stage2_config, prepare_stage2_data

    datamodule = prepare_stage2_data(load_stage2_config(args.overrides))
    print(f"tokens: {datamodule.tokens.folder} ({len(datamodule.tokens)} motions)")
    print(f"caption embeddings: {len(datamodule.caption_cache)} captions ({datamodule.text_encoder.identity})")


def cmd_evaluate(args: argparse.Namespace) -> None:
    from mmm.evaluation.run import evaluate, load_evaluate_config

    results = evaluate(load_evaluate_config(args.overrides))
    print(results["table"])
    if results.get("run_id"):
        print(f"MLflow run: {results['run_id']} (experiment mmm-evaluation)")


def cmd_ablate(args: argparse.Namespace) -> None:
    from mmm.evaluation.ablation import load_ablation_config, run_ablation

    result = run_ablation(args.kind, load_ablation_config(args.overrides))
    print(result["table"])
    for path in result["files"]:
        print(f"wrote {path}")


def cmd_pipeline(args: argparse.Namespace) -> None:
    from mmm.pipeline.steps import load_pipeline_config, run_pipeline

    reports = run_pipeline(args.name, load_pipeline_config(args.overrides), force=args.force, overrides=args.overrides)
    for r in reports:
        print(f"{r.name:22s} {r.status:8s} {r.seconds:7.1f} s  " + ", ".join(f"{k}={v}" for k, v in r.outputs.items() if k in ("run_id", "version", "alias")))
        if r.outputs.get("reason"):
            print(f"{'':22s} {r.outputs['reason']}")


def cmd_promote(args: argparse.Namespace) -> None:
    from mmm.registry.promote import load_promote_config, promote

    decision = promote(args.kind, load_promote_config(args.overrides))
    name = {"tokenizer": "mmm-tokenizer", "text2motion": "mmm-text2motion", "evaluator": "mmm-evaluator", "upperbody": "mmm-upperbody"}[args.kind]
    print(f"{name} version {decision.version} -> {decision.alias}: {decision.reason}")
    for line in decision.comparisons:
        print(f"  {line}")


def cmd_import(args: argparse.Namespace) -> None:
    from mmm.released.importer import UPPER_BODY_REFUSAL, import_released

    if args.kind == "released-upperbody":
        raise CLIError(UPPER_BODY_REFUSAL)
    result = import_released(args.vq, args.stats, args.transformer, args.clip, args.clip_vocab, args.alias, args.heads, args.out_dir,
                             args.tracking_uri, register=not args.no_register)
    print(f"tokenizer checkpoint: {result.tokenizer_checkpoint}")
    if result.transformer_checkpoint:
        print(f"transformer checkpoint: {result.transformer_checkpoint}")
    if result.tokenizer_version:
        print(f"registered{' (already imported: reused)' if result.reused else ''}: models:/mmm-tokenizer/{result.tokenizer_version} "
              f"(@{result.alias})" + (f", models:/mmm-text2motion/{result.text2motion_version} (@{result.alias})" if result.text2motion_version else ""))
    if result.text2motion_version:
        print(f"generate with: mmm generate --model models:/mmm-text2motion@{result.alias} --text '...' --length 120 --out outputs/gen"
              " [--decoding released]")


def cmd_export(args: argparse.Namespace) -> None:
    import torch

    from mmm.generation.model import TextToMotion
    from mmm.released.importer import export_released

    model = TextToMotion.load(args.model, tracking_uri=args.tracking_uri)
    net, trans = export_released(model.tokenizer, model.transformer)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, obj in (("vq.pth", net), ("trans.pth", trans)):
        tmp = out / f".{name}.tmp"
        torch.save(obj, tmp)
        tmp.replace(out / name)
        print(f"wrote {out / name}")


def cmd_dashboard(args: argparse.Namespace) -> None:
    from mlflow.tracking import MlflowClient

    from mmm.tracking import dashboard_links
    from mmm.tracking import resolve_tracking_uri

    base = args.url or f"http://{args.host}:{args.port}"
    print(f"The MLflow dashboard (make mlflow-ui serves it on {base}); each experiment in its training view:")
    for line in dashboard_links(MlflowClient(resolve_tracking_uri(args.tracking_uri)), base):
        print(f"  {line}")


def cmd_models(args: argparse.Namespace) -> None:
    from mlflow.tracking import MlflowClient

    from mmm.registry.versions import list_models
    from mmm.tracking import resolve_tracking_uri

    print(list_models(MlflowClient(resolve_tracking_uri(args.tracking_uri))))


def _sampling(args: argparse.Namespace):
    from mmm.generation.sampler import SamplingConfig
    from mmm.generation.upper_body import UPPER_BODY_GUIDANCE

    guidance = args.guidance if args.guidance is not None else (UPPER_BODY_GUIDANCE if getattr(args, "kind", None) == "upper-body" else 1.0)
    return SamplingConfig(
        max_iterations=args.iterations, schedule=args.schedule, temperature=args.temperature, top_k=args.top_k,
        top_p=args.top_p, guidance_scale=guidance, decoding=args.decoding,
    )


# The command-line option of each range-checked value (SamplingValueError.field -> option).
_OPTION_OF_FIELD = {
    "max_iterations": "--iterations", "temperature": "--temperature", "top_k": "--top-k", "top_p": "--top-p",
    "guidance_scale": "--guidance", "seed": "--seed", "num_samples": "--num-samples",
}


def _option_error(e) -> CLIError:
    """A SamplingValueError in the command line's words: the option, the value, the allowed range."""
    return CLIError(f"{_OPTION_OF_FIELD.get(e.field, e.field)} {e.value} is not allowed: {e.allowed}")


def _check_generation_args(args: argparse.Namespace) -> None:
    """Refuse out-of-range sampling settings, seeds, sample counts and placements before any model
    is loaded or anything written. The ranges are those of mmm.generation.sampler, which the
    served bundle checks its requests against too."""
    from mmm.generation.sampler import SamplingValueError, check_count, check_seed

    try:
        _sampling(args)  # SamplingConfig checks its own fields
        check_seed(args.seed)
        if getattr(args, "num_samples", None) is not None:
            check_count(args.num_samples, "num_samples")
    except SamplingValueError as e:
        raise _option_error(e) from None
    if getattr(args, "place", 0) < 0:
        raise CLIError(f"--place {args.place} is not allowed: the output frame where the source starts, 0 or more (a multiple of 4)")
    if getattr(args, "transition_codes", 0) < 0:
        raise CLIError(f"--transition-codes {args.transition_codes} is not allowed: 0 or more codes between neighbouring segments")


def _load_model(args: argparse.Namespace):
    from mmm.generation.model import TextToMotion

    text_files = {"weights": args.clip_weights, "vocab": args.clip_vocab}
    return TextToMotion.load(args.model, tracking_uri=args.tracking_uri, output_dir=args.stage2_dir, device=args.device, length_model=args.length_model,
                             parts=getattr(args, "kind", None) == "upper-body", stage1=args.stage1,
                             text_files={k: v for k, v in text_files.items() if v is not None})


def _meta(args, model, out, kind: str, extra: dict) -> dict:
    from dataclasses import asdict

    return {"kind": kind, "seed": args.seed, "model": model.identity, "sampling": asdict(_sampling(args)),
            "seconds": {k: round(v, 4) for k, v in out.seconds.items()}, "forward_passes": out.forward_passes, **extra}


def _parse_keep(text: str) -> list[tuple[int, int]]:
    ranges = []
    for part in text.split(","):
        try:
            a, b = (int(x) for x in part.split(":"))
        except ValueError:
            raise CLIError(f"--keep {text!r}: write frame ranges as START:END[,START:END], e.g. 0:40,150:196") from None
        ranges.append((a, b))
    return ranges


def _check_texts(texts: list[str]) -> None:
    for t in texts:
        if not t or not t.strip():
            raise CLIError("--text is empty: describe the motion, e.g. --text 'a person walks forward'")


def cmd_generate(args: argparse.Namespace) -> None:
    from mmm.generation.outputs import write_samples

    _check_generation_args(args)
    _check_texts([args.text])
    model = _load_model(args)
    if args.length is not None:
        model.check_frames(args.length, "--length")
    out = model.generate([args.text] * args.num_samples, [args.length] * args.num_samples if args.length else None, _sampling(args), args.seed, trace=bool(args.trace))
    samples = [
        {"features": f, "joints": j, "caption": args.text,
         "meta": _meta(args, model, out, "generate", {"prompt": args.text, "length_frames": int(f.shape[0]), "sample": k, "iterations": out.iterations[k]})}
        for k, (f, j) in enumerate(zip(out.features, out.joints))
    ]
    folders = write_samples(args.out, samples, model.skeleton, overwrite=args.overwrite)
    if args.trace:
        from mmm.generation.trace import plot_trace

        print(f"wrote {plot_trace(out.trace, Path(args.out) / 'decoding_trace.png', sample=0, title=args.text)}")
    for folder in folders:
        print(f"wrote {folder}")
    print(f"{len(folders)} samples in {out.seconds['total']:.2f} s ({out.forward_passes} transformer passes)")


def cmd_edit(args: argparse.Namespace) -> None:
    from mmm.generation.outputs import write_samples
    from mmm.motion.features import joints_to_features

    _check_generation_args(args)
    if args.kind == "upper-body":
        from mmm.generation.upper_body import DEFAULT_LOWER_MASK

        if args.keep:
            raise CLIError("upper-body keeps the whole lower body of the source; choose how much of it constrains the upper body with --lower-mask SHARE or --lower-keep A:B")
        if not args.text:
            raise CLIError("upper-body needs --text saying what the upper body does, e.g. --text 'a man punches with both hands'")
        if args.lower_mask is not None and args.lower_keep is not None:
            raise CLIError("give --lower-mask (a share of lower-body codes hidden) or --lower-keep (frame ranges shown), not both")
        if args.lower_mask is not None and not 0.0 <= args.lower_mask <= 1.0:
            raise CLIError(f"--lower-mask {args.lower_mask}: a share between 0 (the lower body constrains fully) and 1 (only the text)")
        keep = _parse_keep(args.lower_keep) if args.lower_keep is not None else None
    else:
        if args.lower_mask is not None or args.lower_keep is not None:
            raise CLIError(f"--lower-mask/--lower-keep are for `mmm edit upper-body`, not {args.kind}")
        if not args.keep:
            raise CLIError(f"{args.kind} needs --keep START:END[,START:END] (source frames to keep)")
        keep = _parse_keep(args.keep)
    if args.text is not None:
        _check_texts([args.text])
    if args.kind == "inbetween" and len(keep) < 2:
        raise CLIError("inbetween keeps a start and an end of the source: --keep 0:40,150:196 (frames)")
    if args.kind == "outpaint" and len(keep) != 1:
        raise CLIError("outpaint keeps one middle range and generates around it: --keep 60:140 [--length N --place P]")
    if args.kind == "complete" and keep[0][0] != 0:
        raise CLIError("complete keeps the start of the source and generates the rest: --keep 0:80 [--length N]")
    source = _load_npy(args.source)
    if source.ndim == 3 and source.shape[1:] in ((22, 3), (21, 3)):
        source = joints_to_features(source.astype(np.float32))
    elif not (source.ndim == 2 and source.shape[1] in (263, 251)):
        raise CLIError(f"{args.source}: shape {source.shape}, expected features (T, 263) or joints (T, 22, 3)")
    if not np.isfinite(source).all():
        raise CLIError(f"{args.source}: contains NaN/Inf values")
    model = _load_model(args)
    caption = f"{args.kind}: {args.text or '(no text)'}"
    if args.kind == "upper-body":
        lower_mask = None if keep is not None else (DEFAULT_LOWER_MASK if args.lower_mask is None else args.lower_mask)
        out = model.edit_upper_body(source.astype(np.float32), args.text, lower_mask, keep, _sampling(args), args.seed, args.num_samples)
        extra = {"source": str(args.source), "prompt": args.text, "lower_mask": lower_mask, "lower_keep_frames": keep}
        kept = [row.astype(int).tolist() for row in out.kept_codes]
        captions = [f"{caption} (lower body shown: {sum(row)}/{len(row)} codes)" for row in kept]
    else:
        out = model.edit(source.astype(np.float32), keep, args.text, args.length, args.place, _sampling(args), args.seed, args.num_samples)
        extra = {"source": str(args.source), "keep_frames": keep, "place": args.place, "prompt": args.text}
        kept = [out.kept_codes.astype(int).tolist()] * len(out.features)
        captions = [caption] * len(out.features)
    samples = [
        {"features": f, "joints": j, "caption": captions[k],
         "meta": _meta(args, model, out, args.kind, {**extra, "kept_codes": kept[k], "length_frames": int(f.shape[0]), "sample": k})}
        for k, (f, j) in enumerate(zip(out.features, out.joints))
    ]
    for folder in write_samples(args.out, samples, model.skeleton, overwrite=args.overwrite):
        print(f"wrote {folder}")


def cmd_generate_long(args: argparse.Namespace) -> None:
    from mmm.generation.outputs import write_samples
    from mmm.generation.prompts import split_paragraph

    _check_generation_args(args)
    if args.paragraph is not None and not args.paragraph.strip():
        raise CLIError("--paragraph is empty: describe the motions in order, e.g. --paragraph 'A person walks forward, then jumps.'")
    if bool(args.text) == bool(args.paragraph):
        raise CLIError("give the prompts either as --text ... --text ... or as one --paragraph '...'")
    texts = args.text or split_paragraph(args.paragraph)
    _check_texts(texts)
    try:
        lengths = [int(x) for x in args.lengths.split(",")] if args.lengths else None
    except ValueError:
        raise CLIError(f"--lengths {args.lengths!r}: write frames per segment as whole numbers, one for all or one per prompt, e.g. 80,120") from None
    if lengths is not None and len(lengths) not in (1, len(texts)):
        raise CLIError(f"--lengths has {len(lengths)} values for {len(texts)} prompts")
    if lengths is not None and len(lengths) == 1:
        lengths = lengths * len(texts)
    model = _load_model(args)
    for n in lengths or []:
        model.check_frames(n, "segment length")
    out = model.generate_long(texts, lengths, _sampling(args), args.seed, args.transition_codes)
    meta = _meta(args, model, out, "generate-long", {"prompts": texts, "segments_frames": out.segments, "length_frames": int(out.features[0].shape[0])})
    caption = " / ".join(texts)
    for folder in write_samples(args.out, [{"features": out.features[0], "joints": out.joints[0], "caption": caption, "meta": meta}], model.skeleton, overwrite=args.overwrite):
        print(f"wrote {folder}")
    print(f"{len(texts)} prompts, {out.features[0].shape[0]} frames ({out.features[0].shape[0] / model.fps:.1f} s) in {out.seconds['total']:.2f} s")


def _add_generation_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="output folder: one sub-folder per sample")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--model", default=None, help="stage-2 checkpoint, MLflow run id or models:/NAME@ALIAS (default: the champion, else the newest "
                   "stage-2 result; for upper-body: mmm-upperbody's champion, else the newest part-aware result)")
    p.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    p.add_argument("--length-model", default=None, help="length estimator used when no length is given (default: the newest `make train-length` result)")
    # Files a checkpoint records are read only from outputs/ (or its MLflow run): these name them otherwise.
    p.add_argument("--stage1", default=None, help="the stage-1 model the --model was trained with (checkpoint, run id or models:/...), "
                   "when the file its checkpoint records lies outside outputs/")
    p.add_argument("--clip-weights", default=None, help="the CLIP weights file a CLIP model was trained with, when its recorded path lies outside outputs/")
    p.add_argument("--clip-vocab", default=None, help="the CLIP vocabulary file (bpe_simple_vocab_16e6.txt.gz), likewise")
    p.add_argument("--stage2-dir", default="outputs/stage2", help=argparse.SUPPRESS)
    p.add_argument("--device", default="cpu")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder of earlier samples whole (never a mix of old and new)")
    g = p.add_argument_group("sampling")
    g.add_argument("--iterations", type=int, default=10, help="T_max (each sample runs ceil(T_max * L / 50))")
    g.add_argument("--schedule", choices=["cosine", "linear", "square"], default="cosine")
    g.add_argument("--temperature", type=float, default=1.0)
    g.add_argument("--top-k", type=float, default=None, help="fraction of the codebook kept, e.g. 0.9")
    g.add_argument("--top-p", type=float, default=None)
    g.add_argument("--guidance", type=float, default=None, help="classifier-free guidance scale (1: none; default 1, 4 for upper-body edits)")
    g.add_argument("--decoding", choices=["package", "released"], default="package",
                   help="released: the authors' decoding loop (to compare outputs and speed with imported weights like for like)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mmm", description="MMM: text-to-motion training, generation and tracking")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    convert = sub.add_parser("convert", help="joint positions <-> 263-d features")
    convert.add_argument("direction", choices=["joints-to-features", "features-to-joints"])
    convert.add_argument("input", help="(T, 22, 3) joints or (T, 263) features .npy")
    convert.add_argument("output", help=".npy to write")
    convert.add_argument("--no-retarget", action="store_true", help="keep the motion's own bone lengths")
    convert.set_defaults(func=cmd_convert)

    data = sub.add_parser("data", help="datasets: synthesize, statistics, checks, previews").add_subparsers(dest="data_command", required=True)
    synth = data.add_parser("synth", help="generate the synthetic text-motion dataset")
    synth.add_argument("--out", required=True)
    synth.add_argument("--num-clips", type=int, default=1500)
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    synth.set_defaults(func=cmd_data_synth)

    stats = data.add_parser("stats", help="Mean/Std of a dataset computed the reference way")
    stats.add_argument("root")
    stats.add_argument("--skeleton", choices=["t2m", "kit"], default="t2m")
    stats.add_argument("--write", action="store_true", help="write Mean.npy and Std.npy into the dataset (--evaluator-style: evaluator_style/{mean,std}.npy)")
    stats.add_argument("--evaluator-style", action="store_true",
                       help="the released recipe's statistics: root (dims 0-3) and foot-contact (last 4) Std divided by --feat-bias")
    stats.add_argument("--feat-bias", type=float, default=25.0)
    stats.set_defaults(func=cmd_data_stats)

    check = data.add_parser("check", help="load every split and report what is kept and left out")
    check.add_argument("root")
    check.add_argument("--skeleton", choices=["t2m", "kit"], default="t2m")
    check.add_argument("--min-length", type=int, default=None)
    check.add_argument("--on-invalid", choices=["error", "skip"], default="skip")
    check.set_defaults(func=cmd_data_check)

    preview = data.add_parser("preview", help="render a few clips of a dataset (one per action when labelled)")
    preview.add_argument("root")
    preview.add_argument("--out", required=True)
    preview.add_argument("--count", type=int, default=6)
    preview.add_argument("--split", default="test")
    preview.set_defaults(func=cmd_data_preview)

    train = sub.add_parser("train", help="train a stage; any config key can be overridden as key=value")
    train.add_argument("stage", choices=["stage1", "stage2", "length", "evaluator", "stage1-parts", "stage2-parts"],
                       help="stage1-parts/stage2-parts: the part-aware model for upper-body editing")
    train.add_argument("overrides", nargs="*", help="e.g. trainer.max_steps=500 model=paper data=humanml3d")
    train.add_argument("--resume", default=None, help="'last' (newest run of this stage that no other process is writing) or a checkpoint "
                       "path (one outside this stage's run folders is only read: the run goes on in a new run folder)")
    train.set_defaults(func=cmd_train)

    tokenize = sub.add_parser("tokenize", help="tokenize a dataset with a stage-1 model and cache caption embeddings (stage 2's inputs)")
    tokenize.add_argument("overrides", nargs="*", help="stage 2's config keys, e.g. stage1=RUN_ID data=humanml3d")
    tokenize.set_defaults(func=cmd_tokenize)

    gen = sub.add_parser("generate", help="text to motion")
    gen.add_argument("--text", required=True)
    gen.add_argument("--length", type=int, default=None, help="frames (40-196 at 20 fps); estimated from the text when left out")
    gen.add_argument("--num-samples", type=int, default=1)
    gen.add_argument("--trace", action="store_true", help="also plot the decoding (confidence and mask per iteration)")
    _add_generation_options(gen)
    gen.set_defaults(func=cmd_generate)

    edit = sub.add_parser("edit", help="edit a motion: keep some frames and generate the rest, or give it a new upper body")
    edit.add_argument("kind", choices=["inbetween", "outpaint", "complete", "upper-body"])
    edit.add_argument("--source", required=True, help="features (T, 263) or joints (T, 22, 3) .npy")
    edit.add_argument("--keep", default=None, help="source frames to keep: START:END[,START:END] (inbetween, outpaint, complete)")
    edit.add_argument("--lower-mask", type=float, default=None,
                      help="upper-body: share of the source's lower-body codes hidden from the model (0: the lower body constrains fully; default 0.5)")
    edit.add_argument("--lower-keep", default=None, help="upper-body: source frames whose lower-body codes constrain the upper body, START:END[,...]")
    edit.add_argument("--text", default=None, help="what the generated part shows (none: without text)")
    edit.add_argument("--length", type=int, default=None, help="output frames (default: the source's)")
    edit.add_argument("--place", type=int, default=0, help="output frame where the source starts (a multiple of 4)")
    edit.add_argument("--num-samples", type=int, default=1)
    _add_generation_options(edit)
    edit.set_defaults(func=cmd_edit)

    long = sub.add_parser("generate-long", help="one long motion from several prompts or a paragraph")
    long.add_argument("--text", action="append", help="one per segment, in order")
    long.add_argument("--paragraph", default=None, help="split into prompts by a deterministic splitter")
    long.add_argument("--lengths", default=None, help="frames per segment: one value for all, or one per prompt (comma-separated)")
    long.add_argument("--transition-codes", type=int, default=2, help="codes generated between neighbouring segments")
    _add_generation_options(long)
    long.set_defaults(func=cmd_generate_long)

    evaluate = sub.add_parser("evaluate", help="the evaluation protocol, reconstruction metrics and prompt adherence, logged to MLflow")
    evaluate.add_argument("overrides", nargs="*", help="e.g. text2motion=RUN_ID protocol.replications=5 evaluator.reference=t2m:/ckpt/t2m")
    evaluate.set_defaults(func=cmd_evaluate)

    ablate = sub.add_parser("ablate", help="the supplementary's ablation tables (8-13) as sweeps")
    ablate.add_argument("kind", choices=["reset", "cross-layers", "schedule", "temperature", "topk", "topp"])
    ablate.add_argument("overrides", nargs="*", help="e.g. grids.temperature=[0.5,1.0] protocol.replications=5")
    ablate.set_defaults(func=cmd_ablate)

    pipeline = sub.add_parser("pipeline", help="stages chained as one MLflow parent run; unchanged steps are skipped")
    pipeline.add_argument("name", choices=["full", "stage1", "stage2", "evaluate", "promote", "parts"])
    pipeline.add_argument("overrides", nargs="*", help="e.g. overrides.stage1=[trainer.max_steps=500] data=humanml3d")
    pipeline.add_argument("--force", action="append", default=[], help="rerun this step even if its inputs did not change (or 'all')")
    pipeline.set_defaults(func=cmd_pipeline)

    promote = sub.add_parser("promote", help="measure a candidate, register it, move `champion` only when it wins")
    promote.add_argument("kind", choices=["tokenizer", "text2motion", "evaluator", "upperbody"])
    promote.add_argument("overrides", nargs="*", help="e.g. candidate=RUN_ID criteria.text2motion=[{metric: generated/fid, mode: min, margin: 0.01}]")
    promote.set_defaults(func=cmd_promote)

    imp = sub.add_parser("import", help="the authors' released checkpoints as this package's models, registered in MLflow")
    imp.add_argument("kind", choices=["released", "released-upperbody"],
                     help="released: the text-to-motion pair; released-upperbody: refused (see the README)")
    imp.add_argument("--vq", required=True, help="released stage-1 checkpoint ({'net': state_dict}, e.g. output/vq/.../net_last.pth)")
    imp.add_argument("--transformer", default=None, help="released stage-2 checkpoint ({'trans': state_dict}); left out: the tokenizer only")
    imp.add_argument("--stats", required=True, help="folder with the mean.npy/std.npy the release normalizes with (the T2M evaluator's meta folder)")
    imp.add_argument("--clip", default=None, help="OpenAI CLIP ViT-B/32 weights (ViT-B-32.pt, read without running it) or open_clip's")
    imp.add_argument("--clip-vocab", default=None, help="bpe_simple_vocab_16e6.txt.gz (default: the one inside an installed open_clip)")
    imp.add_argument("--alias", default="released", help="alias given to the registered versions (not champion: promotion moves that)")
    imp.add_argument("--heads", type=int, default=None, help="attention heads (default: embedding width / 64, the release's 16)")
    imp.add_argument("--out-dir", default="outputs/imported", help="where this package's checkpoints are written")
    imp.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    imp.add_argument("--no-register", action="store_true", help="only write the checkpoints")
    imp.set_defaults(func=cmd_import)

    exp = sub.add_parser("export", help="a model in the authors' released file layout")
    exp.add_argument("kind", choices=["released"])
    exp.add_argument("--model", required=True, help="a released-variant model: checkpoint, run id or models:/NAME@ALIAS")
    exp.add_argument("--out", required=True, help="folder for vq.pth ({'net': ...}) and trans.pth ({'trans': ...})")
    exp.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    exp.set_defaults(func=cmd_export)

    dash = sub.add_parser("dashboard", help="links into the MLflow dashboard: every experiment in its training view, its newest run, the models")
    dash.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    dash.add_argument("--host", default="127.0.0.1")
    dash.add_argument("--port", type=int, default=5000)
    dash.add_argument("--url", default=None, help="the dashboard's address when it is served elsewhere (e.g. a team server)")
    dash.set_defaults(func=cmd_dashboard)

    models = sub.add_parser("models", help="registered models").add_subparsers(dest="models_command", required=True)
    listing = models.add_parser("list", help="versions, aliases and metrics of the registered models")
    listing.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    listing.set_defaults(func=cmd_models)

    render = sub.add_parser("render", help="stick-figure GIF/MP4/PNG of motions side by side")
    render.add_argument("inputs", nargs="+", help=".npy files of joints (T, 22, 3) or features (T, 263)")
    render.add_argument("--out", required=True, help="FILE.gif, FILE.mp4 or FILE.png (contact sheet)")
    render.add_argument("--caption", action="append", help="one per input, in order")
    render.add_argument("--fps", type=float, default=None)
    render.set_defaults(func=cmd_render)
    return parser


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is at the time (not the one at set-up), so that `main` can be
    called again after stderr was replaced, as tests and notebooks do."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass


def _configure_logging(verbose: bool) -> None:
    """This package's INFO lines and everyone's warnings, once each (Lightning prints its own
    INFO lines through its own handler)."""
    fmt = logging.Formatter("%(levelname)s %(name)s: %(message)s")
    logging.basicConfig(level=logging.WARNING, handlers=[_StderrHandler()])
    for handler in logging.getLogger().handlers:
        handler.setLevel(logging.DEBUG if verbose else logging.WARNING)
        handler.setFormatter(fmt)
    ours = logging.getLogger("mmm")
    ours.setLevel(logging.DEBUG if verbose else logging.INFO)
    if not ours.handlers:
        handler = _StderrHandler()
        handler.setFormatter(fmt)
        ours.addHandler(handler)
        ours.propagate = False


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _configure_logging(args.verbose)
    from mmm.config import ConfigError
    from mmm.data.humanml3d import DataError

    try:
        args.func(args)
    except (CLIError, DataError, ConfigError, FileExistsError, FileNotFoundError, ValueError) as e:
        if args.verbose:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

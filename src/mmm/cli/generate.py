"""Generation commands: generate, edit, generate-long (the options they share: options.py)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from mmm.cli.common import CLIError, load_npy
from mmm.cli.options import (
    add_generation_options,
    check_device_option,
    check_generation_args,
    check_texts,
    cut_texts,
    length_meta,
    load_model,
    meta,
    sampling_config,
)
from mmm.generation.edits import EDIT_KINDS, UPPER_BODY
from mmm.generation.settings import MAX_SAMPLES, check_candidates

# How `mmm edit` spells the fields of an edit request in its messages.
EDIT_OPTIONS = {
    "text": "--text",
    "keep": "--keep",
    "lower_mask": "--lower-mask",
    "lower_keep": "--lower-keep",
    "place": "--place",
    "length": "--length",
}


def add_best_of_options(parser, kept: str) -> None:
    parser.add_argument(
        "--candidates",
        type=int,
        default=1,
        help=f"best of N: draw N motions per sample and keep {kept} "
        "(from text, 4 with --guidance 1.5 follows the most prompts, README 'Best of N'; about N times "
        "the decoding time; default 1: one draw)",
    )
    parser.add_argument(
        "--judge",
        default=None,
        help="the evaluator that picks among --candidates: a checkpoint, run id or models:/... "
        "(default: the judge a registered --model bundle carries, else models:/mmm-evaluator@champion, "
        "else the newest `make train-evaluator` result)",
    )


def load_best_of_judge(args: argparse.Namespace, model):
    """--judge, else the judge the model's registered bundle carries (the evaluator it was promoted
    with), else the evaluator champion (mmm.evaluation.evaluators.load_judge)."""
    from mmm.evaluation.evaluators import load_judge

    return load_judge(args.judge or model.judge_checkpoint, args.tracking_uri, args.device)


def check_best_of_args(args: argparse.Namespace) -> None:
    try:
        check_candidates(args.candidates, "--candidates")
    except ValueError as e:
        raise CLIError(str(e)) from None


def add_generate(sub) -> None:
    gen = sub.add_parser("generate", help="text to motion")
    gen.add_argument(
        "--text",
        action="append",
        required=True,
        help="what the motion shows; repeat it for several prompts, drawn in one batch with one model "
        "load: the sample folders hold --num-samples samples of each prompt, in the order given",
    )
    gen.add_argument(
        "--length",
        type=int,
        default=None,
        help="frames (HumanML3D models: 40-196 at 20 fps; KIT-ML: 24-196 at 12.5 fps); estimated from the "
        "text when left out",
    )
    gen.add_argument("--num-samples", type=int, default=1)
    gen.add_argument(
        "--trace", action="store_true", help="also plot the decoding (confidence and mask per iteration)"
    )
    add_best_of_options(gen, "the one the judge puts closest to the text")
    add_generation_options(gen)
    gen.set_defaults(func=cmd_generate)


def add_edit(sub) -> None:
    edit = sub.add_parser(
        "edit", help="edit a motion: keep some frames and generate the rest, or give it a new upper body"
    )
    edit.add_argument("kind", choices=list(EDIT_KINDS))
    edit.add_argument("--source", required=True, help="features (T, 263) or joints (T, 22, 3) .npy")
    edit.add_argument(
        "--keep",
        default=None,
        help="source frames to keep: START:END[,START:END] (inbetween, outpaint, complete)",
    )
    edit.add_argument(
        "--lower-mask",
        type=float,
        default=None,
        help="upper-body: share of the source's lower-body codes hidden from the model "
        "(0: the lower body constrains fully; default 0.5)",
    )
    edit.add_argument(
        "--lower-keep",
        default=None,
        help="upper-body: source frames whose lower-body codes constrain the upper body, START:END[,...]",
    )
    edit.add_argument("--text", default=None, help="what the generated part shows (none: without text)")
    edit.add_argument("--length", type=int, default=None, help="output frames (default: the source's)")
    edit.add_argument(
        "--place", type=int, default=0, help="output frame where the source starts (a multiple of 4)"
    )
    edit.add_argument("--num-samples", type=int, default=1)
    add_best_of_options(edit, "the one whose edited frames the judge puts closest to --text")
    add_generation_options(edit)
    edit.set_defaults(func=cmd_edit)


def add_generate_long(sub) -> None:
    long = sub.add_parser("generate-long", help="one long motion from several prompts or a paragraph")
    long.add_argument("--text", action="append", help="one per segment, in order")
    long.add_argument("--paragraph", default=None, help="split into prompts by a deterministic splitter")
    long.add_argument(
        "--lengths",
        default=None,
        help="frames per segment: one value for all, or one per prompt (comma-separated)",
    )
    long.add_argument(
        "--transition-codes", type=int, default=2, help="codes generated between neighbouring segments"
    )
    add_best_of_options(long, "for every prompt the segment the judge puts closest to it")
    add_generation_options(long)
    long.set_defaults(func=cmd_generate_long)


def cmd_generate(args: argparse.Namespace) -> None:
    check_generation_args(args)
    check_texts(args.text)
    check_best_of_args(args)
    total = len(args.text) * args.num_samples
    if total > MAX_SAMPLES:
        raise CLIError(
            f"{len(args.text)} prompts x --num-samples {args.num_samples} is {total} samples; at most "
            f"{MAX_SAMPLES} per call: split the prompts over several calls"
        )
    if args.candidates > 1 and args.trace:
        raise CLIError(
            "--trace plots one draw's decoding: leave it out with --candidates, or use --candidates 1"
        )
    check_device_option(args)
    # imported after the checks: keeps `mmm --help` and refusing bad input fast (no model libraries)
    from mmm.generation.best_of import generate_best_of
    from mmm.generation.outputs import write_samples

    model = load_model(args)
    if args.length is not None:
        model.check_frames(args.length, "--length")
    judge = load_best_of_judge(args, model) if args.candidates > 1 else None
    judged = {"candidates": args.candidates, "judge": judge.identity} if judge else {}
    # One call per prompt, each with --seed: a prompt's samples do not depend on the other prompts
    # given with it (one batch would share the random stream). Prompt-major: sample folder
    # i * num_samples + k is sample k of prompt i.
    texts = [text for text in args.text for _ in range(args.num_samples)]
    lengths = [args.length] * args.num_samples if args.length else None
    calls, sampling = [], sampling_config(args)
    for i, prompt in enumerate(args.text):
        batch = [prompt] * args.num_samples
        if judge:
            calls.append(generate_best_of(model, judge, batch, lengths, args.candidates, sampling, args.seed))
        else:
            trace = bool(args.trace) and i == 0  # the plot shows the first sample only
            calls.append(model.generate(batch, lengths, sampling, args.seed, trace=trace))
    out = concatenate_calls(calls)
    cut = cut_texts(model, args.text)
    samples = [
        {
            "features": f,
            "joints": j,
            "caption": texts[k],
            "meta": meta(
                args,
                model,
                out,
                "generate",
                {
                    "prompt": texts[k],
                    "length_frames": int(f.shape[0]),
                    **length_meta(model, given=lengths is not None),
                    "sample": k % args.num_samples,
                    "iterations": out.iterations[k],
                    **({"text_cut": cut[texts[k]]} if texts[k] in cut else {}),
                    **judged,
                    **({"judge_scores": [round(float(v), 4) for v in out.scores[k]]} if judged else {}),
                },
            ),
        }
        for k, (f, j) in enumerate(zip(out.features, out.joints))
    ]
    folders = write_samples(args.out, samples, model.skeleton, overwrite=args.overwrite)
    if args.trace:
        from mmm.generation.trace import plot_trace

        trace = plot_trace(out.trace, Path(args.out) / "decoding_trace.png", sample=0, title=texts[0])
        print(f"wrote {trace}")
    for folder in folders:
        print(f"wrote {folder}")
    prompts = f" of {len(args.text)} prompts" if len(args.text) > 1 else ""
    print(
        f"{len(folders)} sample{'s' if len(folders) != 1 else ''}{prompts} in {out.seconds['total']:.2f} s "
        f"({out.forward_passes} transformer passes)"
    )


def concatenate_calls(calls: list):
    """Several `Generated` results as one: samples in call order, seconds and passes summed, the
    first call's trace."""
    from dataclasses import replace

    seconds: dict[str, float] = {}
    for call in calls:
        for key, value in call.seconds.items():
            seconds[key] = seconds.get(key, 0.0) + value
    scores = [call.scores for call in calls]
    return replace(
        calls[0],
        texts=[t for call in calls for t in call.texts],
        features=[f for call in calls for f in call.features],
        joints=[j for call in calls for j in call.joints],
        codes=[c for call in calls for c in call.codes],
        iterations=[n for call in calls for n in call.iterations],
        forward_passes=sum(call.forward_passes for call in calls),
        seconds=seconds,
        scores=None if scores[0] is None else np.concatenate(scores),
    )


def cmd_edit(args: argparse.Namespace) -> None:
    from mmm.generation.edits import EditRequest

    check_generation_args(args)
    check_best_of_args(args)
    if args.candidates > 1 and not args.text:
        raise CLIError(
            "--candidates: best of N judges the edited frames against --text; give --text, or leave "
            "--candidates out"
        )
    request = EditRequest.parse(
        args.kind,
        text=args.text,
        keep=args.keep,
        lower_mask=args.lower_mask,
        lower_keep=args.lower_keep,
        length=args.length,
        place=args.place,
        names=EDIT_OPTIONS,
    )
    source = load_npy(args.source)
    given = f"{source.shape}"
    if source.ndim == 3 and source.shape[1:] in ((22, 3), (21, 3)):
        from mmm.motion.features import joints_to_features  # imported here: it needs torch

        source = joints_to_features(source.astype(np.float32))
        given = f"joints {given}, read as features {source.shape}"
        # the features hold the motion between joint frames: one frame fewer, which --keep counts
        print(
            f"{args.source}: {given} (one frame fewer: --keep, --place and --lower-keep count feature "
            "frames)",
            file=sys.stderr,
        )
    elif not (source.ndim == 2 and source.shape[1] in (263, 251)):
        raise CLIError(
            f"{args.source}: shape {source.shape}, expected features (T, 263) or joints (T, 22, 3)"
        )
    if not np.isfinite(source).all():
        raise CLIError(f"{args.source}: contains NaN/Inf values")
    check_device_option(args)
    # imported after the checks: keeps `mmm --help` and refusing bad input fast (no model libraries)
    from mmm.generation.best_of import edit_best_of
    from mmm.generation.outputs import write_samples

    model = load_model(args)
    if source.shape[1] != model.feature_dim:
        raise CLIError(
            f"{args.source}: {given}, but the model reads {model.feature_dim}-d features "
            f"({'HumanML3D, 22 joints' if model.feature_dim == 263 else 'KIT-ML, 21 joints'}): give a source "
            "of its skeleton, or a model trained on this one"
        )
    if source.shape[0] < model.unit:
        raise CLIError(
            f"{args.source}: {source.shape[0]} frames of features; an edit needs at least {model.unit} "
            "(one code of the tokenizer): give a longer source"
        )
    source = source.astype(np.float32)
    extra = {"source": str(args.source)}
    cut = cut_texts(model, [args.text])
    if cut:
        extra["text_cut"] = cut[args.text]
    if args.candidates > 1:
        judge = load_best_of_judge(args, model)
        out, span = edit_best_of(
            request, model, judge, source, args.candidates, sampling_config(args), args.seed, args.num_samples
        )
        extra |= {"candidates": args.candidates, "judge": judge.identity, "judged_frames": list(span)}
    else:
        out = request.run(model, source, sampling_config(args), args.seed, args.num_samples)
    caption = f"{args.kind}: {args.text or '(no text)'}"
    if args.kind == UPPER_BODY:
        extra |= {
            "prompt": args.text,
            "lower_mask": request.lower_mask,
            "lower_keep_frames": request.lower_keep,
        }
        kept = [row.astype(int).tolist() for row in out.kept_codes]
        captions = [f"{caption} (lower body shown: {sum(row)}/{len(row)} codes)" for row in kept]
    else:
        extra |= {"keep_frames": request.keep, "place": args.place, "prompt": args.text}
        kept = [out.kept_codes.astype(int).tolist()] * len(out.features)
        kept_frames = ", ".join(f"{a}-{b}" for a, b in request.keep)
        captions = [f"{caption} (source frames {kept_frames} kept)"] * len(out.features)
    placed = f", frame 0 at the edit's frame {args.place}" if args.kind != UPPER_BODY and args.place else ""
    reference = (model.to_joints(source), f"source {Path(args.source).name}{placed}")
    samples = [
        {
            "features": f,
            "joints": j,
            "caption": captions[k],
            "meta": meta(
                args,
                model,
                out,
                args.kind,
                {
                    **extra,
                    "kept_codes": kept[k],
                    "length_frames": int(f.shape[0]),
                    "sample": k,
                    **(
                        {"judge_scores": [round(float(v), 4) for v in out.scores[k]]}
                        if out.scores is not None
                        else {}
                    ),
                },
            ),
            "reference": reference,
        }
        for k, (f, j) in enumerate(zip(out.features, out.joints))
    ]
    for folder in write_samples(args.out, samples, model.skeleton, overwrite=args.overwrite):
        print(f"wrote {folder}")


def cmd_generate_long(args: argparse.Namespace) -> None:
    from mmm.generation.prompts import split_paragraph

    check_generation_args(args)
    check_best_of_args(args)
    if args.paragraph is not None and not args.paragraph.strip():
        raise CLIError(
            "--paragraph is empty: describe the motions in order, "
            "e.g. --paragraph 'A person walks forward, then jumps.'"
        )
    if bool(args.text) == bool(args.paragraph):
        raise CLIError("give the prompts either as --text ... --text ... or as one --paragraph '...'")
    texts = args.text or split_paragraph(args.paragraph)
    check_texts(texts)
    try:
        lengths = [int(x) for x in args.lengths.split(",")] if args.lengths else None
    except ValueError:
        raise CLIError(
            f"--lengths {args.lengths!r}: write frames per segment as whole numbers, one for all "
            "or one per prompt, e.g. 80,120"
        ) from None
    if lengths is not None and len(lengths) not in (1, len(texts)):
        raise CLIError(f"--lengths has {len(lengths)} values for {len(texts)} prompts")
    if lengths is not None and len(lengths) == 1:
        lengths = lengths * len(texts)
    check_device_option(args)
    # imported after the checks: keeps `mmm --help` and refusing bad input fast (no model libraries)
    from mmm.generation.best_of import generate_long_best_of
    from mmm.generation.outputs import write_samples

    model = load_model(args)
    for n in lengths or []:
        model.check_frames(n, "segment length")
    judged = {}
    if args.candidates > 1:
        judge = load_best_of_judge(args, model)
        sampling = sampling_config(args)
        out = generate_long_best_of(
            model, judge, texts, lengths, args.candidates, sampling, args.seed, args.transition_codes
        )
        judged = {
            "candidates": args.candidates,
            "judge": judge.identity,
            "judge_scores": [[round(float(v), 4) for v in row] for row in out.scores],
        }
    else:
        out = model.generate_long(texts, lengths, sampling_config(args), args.seed, args.transition_codes)
    frames = int(out.features[0].shape[0])
    cut = cut_texts(model, texts)
    info = meta(
        args,
        model,
        out,
        "generate-long",
        {
            "prompts": texts,
            "segments_frames": out.segments,
            "length_frames": frames,
            **length_meta(model, given=lengths is not None),
            **({"texts_cut": cut} if cut else {}),
            **judged,
        },
    )
    caption = " / ".join(texts)
    spans = [(a, b, f"{i}. {text}") for i, (text, (a, b)) in enumerate(zip(texts, out.segments), 1)]
    sample = {
        "features": out.features[0],
        "joints": out.joints[0],
        "caption": caption,
        "meta": info,
        "spans": spans,
    }
    for folder in write_samples(args.out, [sample], model.skeleton, overwrite=args.overwrite):
        print(f"wrote {folder}")
    seconds = out.seconds["total"]
    prompts = f"{len(texts)} prompt" + ("s" if len(texts) != 1 else "")
    print(f"{prompts}, {frames} frames ({frames / model.fps:.1f} s) in {seconds:.2f} s:")
    for a, b, label in spans:
        print(f"  {label} (frames {a}-{b})")

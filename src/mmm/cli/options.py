"""The options generate, edit and generate-long share, and what they do with them: load the model,
check the sampling settings, build the SamplingConfig, describe a sample in its meta.json.

The sampling flags are SamplingConfig's fields (generation/settings.py: a field's metadata
gives its flag, help text and choices). Each flag's default is None, "not given": SamplingConfig's
own default applies then, or the edit kind's (upper-body edits sample with guidance 4).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import fields

from mmm.cli.common import DEFAULT_TRACKING_URI, CLIError
from mmm.generation.edits import UPPER_BODY, sampling_defaults
from mmm.generation.settings import (
    DEFAULT_PRECISION,
    PRECISIONS,
    SamplingConfig,
    SamplingValueError,
    check_count,
    check_seed,
)
from mmm.kinds import KINDS

# The command-line option of the range-checked values that are not sampling settings
# (SamplingValueError.field -> option); those of the sampling settings come from sampling_options().
OPTION_OF_FIELD = {"seed": "--seed", "num_samples": "--num-samples"}
_TYPES = {"int": int, "float": float, "str": str}


def sampling_options() -> list[tuple]:
    """(field, flag) of each SamplingConfig field that is a command-line option."""
    out = []
    for f in fields(SamplingConfig):
        flag = f.metadata["flag"] if "flag" in f.metadata else "--" + f.name.replace("_", "-")
        if flag is not None:
            out.append((f, flag))
    return out


def _dest(flag: str) -> str:
    return flag.lstrip("-").replace("-", "_")


def add_sampling_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("sampling")
    for f, flag in sampling_options():
        annotation = f.type if isinstance(f.type, str) else f.type.__name__  # "float | None": float
        choices = f.metadata.get("choices")
        g.add_argument(
            flag,
            type=_TYPES[annotation.split(" | ")[0]],
            default=None,
            choices=list(choices) if choices else None,
            help=f.metadata.get("help"),
        )


def option_error(e) -> CLIError:
    """A SamplingValueError in the command line's words: the option, the value, the allowed range."""
    options = {**OPTION_OF_FIELD, **{f.name: flag for f, flag in sampling_options()}}
    return CLIError(f"{options.get(e.field, e.field)} {e.value} is not allowed: {e.allowed}")


def add_generation_options(p) -> None:
    p.add_argument("--out", required=True, help="output folder: one sub-folder per sample")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--model",
        default=None,
        help="stage-2 checkpoint, MLflow run id or models:/NAME@ALIAS "
        "(default: the champion, else the newest stage-2 result; for upper-body: mmm-upperbody's "
        "champion, else the newest part-aware result)",
    )
    p.add_argument("--tracking-uri", default=DEFAULT_TRACKING_URI)
    p.add_argument(
        "--length-model",
        default=None,
        help="length estimator used when no length is given (default: the newest `make train-length` result)",
    )
    # Files a checkpoint records are read only from outputs/ (or its MLflow run): these name them otherwise.
    p.add_argument(
        "--stage1",
        default=None,
        help="the stage-1 model the --model was trained with "
        "(checkpoint, run id or models:/...), when the file its checkpoint records lies "
        "outside outputs/",
    )
    p.add_argument(
        "--clip-weights",
        default=None,
        help="the CLIP weights file a CLIP model was trained "
        "with, when its recorded path lies outside outputs/",
    )
    p.add_argument(
        "--clip-vocab", default=None, help="the CLIP vocabulary file (bpe_simple_vocab_16e6.txt.gz), likewise"
    )
    p.add_argument("--stage2-dir", default=KINDS["stage2"].output_dir, help=argparse.SUPPRESS)
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out folder of earlier samples whole (never a mix of old and new)",
    )
    p.defer(add_sampling_options)
    p.defer(add_precision_option)


def add_precision_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--precision",
        default=None,
        choices=list(PRECISIONS),
        help="arithmetic of the transformer's decoding passes: fp32, bf16 (autocast) or int8 (dynamic "
        "int8 linear layers, CPU) (default: "
        + ", ".join(f"{precision} on {device}" for device, precision in DEFAULT_PRECISION.items())
        + ")",
    )
    p.add_argument(
        "--compile",
        action="store_true",
        help="run the decoding passes through torch.compile with static length buckets (CUDA graphs on "
        "a GPU); each new shape compiles on first use, so it pays off over many sentences",
    )


def sampling_config(args: argparse.Namespace):
    """The SamplingConfig of the sampling flags given (it checks its own fields)."""
    given = {f.name: getattr(args, _dest(flag)) for f, flag in sampling_options()}
    given = {k: v for k, v in given.items() if v is not None}
    return SamplingConfig(**{**sampling_defaults(getattr(args, "kind", None)), **given})


def check_generation_args(args: argparse.Namespace) -> None:
    """Refuse out-of-range sampling settings, seeds, sample counts and transition lengths before
    any model is loaded or anything written. The ranges are those of mmm.generation.settings,
    which the served bundle checks its requests against too."""
    try:
        sampling_config(args)
        check_seed(args.seed)
        if getattr(args, "num_samples", None) is not None:
            check_count(args.num_samples, "num_samples")
    except SamplingValueError as e:
        raise option_error(e) from None
    if getattr(args, "transition_codes", 0) < 0:
        raise CLIError(
            f"--transition-codes {args.transition_codes} is not allowed: "
            "0 or more codes between neighbouring segments"
        )


def check_texts(texts: list[str]) -> None:
    for t in texts:
        if not t or not t.strip():
            raise CLIError("--text is empty: describe the motion, e.g. --text 'a person walks forward'")


def check_device_option(args: argparse.Namespace) -> None:
    """Refuse a --device this machine lacks, by name. The last check before a model loads: it is
    the only one that needs torch."""
    # imported here: keeps `mmm --help` and every other refusal fast (this check needs torch)
    from mmm.device import check_device

    try:
        check_device(args.device, "--device")
    except ValueError as e:
        raise CLIError(str(e)) from None


def load_model(args: argparse.Namespace):
    from mmm.generation.model import TextToMotion

    text_files = {"weights": args.clip_weights, "vocab": args.clip_vocab}
    model = TextToMotion.load(
        args.model,
        tracking_uri=args.tracking_uri,
        output_dir=args.stage2_dir,
        device=args.device,
        length_model=args.length_model,
        parts=getattr(args, "kind", None) == UPPER_BODY,
        stage1=args.stage1,
        text_files={k: v for k, v in text_files.items() if v is not None},
        precision=getattr(args, "precision", None),
    )
    model.compiled = getattr(args, "compile", False)
    return model


def cut_texts(model, texts) -> dict[str, dict]:
    """The texts longer than the text encoder reads (`TextEncoder.texts_cut`), for meta.json,
    each named once on stderr."""
    encoder = model.text_encoder
    cut = encoder.texts_cut(texts)
    for text, info in cut.items():
        shown = text if len(text) <= 60 else text[:57] + "..."
        print(
            f"warning: {shown!r} is {info['tokens']} tokens; the text encoder ({encoder.name}) reads its "
            f"first {encoder.max_words}, the rest is left out: shorten it, or split it into prompts "
            "(generate-long --paragraph)",
            file=sys.stderr,
        )
    return cut


def length_meta(model, given: bool) -> dict:
    """Where a sample's length came from, for meta.json: the flag, or the estimator that guessed it."""
    if given:
        return {"length_source": "given"}
    return {"length_source": "estimated", "length_estimator": model.length_estimator_identity}


def meta(args, model, out, kind: str, extra: dict) -> dict:
    from dataclasses import asdict

    seconds = {k: round(v, 4) for k, v in out.seconds.items()}
    sampling = asdict(sampling_config(args))
    return {
        "kind": kind,
        "seed": args.seed,
        "model": model.identity,
        "sampling": sampling,
        "precision": model.precision,
        "compiled": model.compiled,
        "seconds": seconds,
        "forward_passes": out.forward_passes,
        **extra,
    }

"""Reading this package's checkpoints: the one place where a file becomes a checkpoint or a clear error.

    ckpt = load_checkpoint("outputs/stage2/<run>/checkpoints/best.ckpt", "stage2")
    ckpt["hyper_parameters"], ckpt["state_dict"]

Every checkpoint is read with torch.load(weights_only=True): tensors and plain containers only,
no code runs. Whatever else the file turns out to be is a `CheckpointError` (a ValueError, so the
CLI prints it and exits 2) naming the file, what was expected, what was found and what to do:
a missing file, a folder, random bytes or a text file, a truncated archive, a checkpoint of
another kind (a stage-1 model where a stage-2 one is expected, ...), or weights that no longer
have the fingerprint recorded when the checkpoint was saved (`FINGERPRINT_KEY`, written by the
trainers) or the one the caller expects (a registered version's tag).

Hyper-parameters recorded in a checkpoint may name files (the stage-1 checkpoint, CLIP's weights
and vocabulary). `trusted_recorded_path` says when such a recorded path may be followed: only when
it lies inside this package's output folder, `outputs/` of the working directory (where training,
the model cache and the registry bundle cache write). A file elsewhere is used only when the user
names it.
"""

from __future__ import annotations

from pathlib import Path

import torch

from mmm.fingerprint import tensors_fingerprint
from mmm.kinds import KINDS

FINGERPRINT_KEY = "weights_fingerprint"  # tensors_fingerprint(state_dict) at save time
WEIGHT_EMA_KEY = "weight_ema"  # the decay a stage-2 state_dict was averaged with (absent: none)
OUTPUTS_ROOT = "outputs"  # the package's output folder, relative to the working directory

# checkpoint family (the model kind that writes it; the part-aware kinds write the same families)
# -> (what it is, how to make one)
CHECKPOINTS = {
    name: (what, f"`{KINDS[name].train}` writes {KINDS[name].output_dir}/<run>/checkpoints/best.ckpt")
    for name, what in {
        "stage1": "stage-1 (motion tokenizer) checkpoint",
        "stage2": "stage-2 (text-to-motion transformer) checkpoint",
        "length": "length estimator checkpoint",
        "evaluator": "contrastive evaluator checkpoint",
    }.items()
}
# Where each kind is passed, for a file given in the wrong place.
_PASSED_AS = {
    "stage1": "as the stage-1 model (--stage1 PATH, or stage1=PATH in a training config)",
    "stage2": "as the text-to-motion model (--model PATH)",
    "length": "as the length estimator (--length-model PATH)",
    "evaluator": "as the evaluator (evaluator.reference=PATH of `mmm evaluate`)",
}


class CheckpointError(ValueError):
    """A file that is not the checkpoint it should be; the message names the file and the fix."""


def checkpoint_kind(ckpt: dict) -> str | None:
    """ "stage1", "stage2", "length" or "evaluator" from what a checkpoint holds; None: none of them."""
    hp = ckpt.get("hyper_parameters") or {}
    state = ckpt.get("state_dict") or {}
    if not isinstance(hp, dict) or not isinstance(state, dict):
        return None
    if "codebook_shape" in hp:
        return "stage2"
    if any(k.startswith("estimator.") for k in state):
        return "length"
    if any(k.startswith("evaluator.") for k in state):
        return "evaluator"
    if "feature_dim" in hp and "model" in hp and any(k.startswith("tokenizer.") for k in state):
        return "stage1"
    return None


def _describe(ckpt: dict) -> str:
    """What a dict that is none of the package's checkpoints looks like."""
    keys = sorted(map(str, ckpt))[:6]
    if {"net", "trans"} & set(ckpt):
        return f"a released MMM file (keys {', '.join(keys)}); bring it in with `mmm import released` first"
    return f"a dict with keys {', '.join(keys) or 'none'}, not a checkpoint of this package"


def weights_fingerprint(ckpt: dict) -> str:
    return tensors_fingerprint(ckpt.get("state_dict") or {})


def read_torch_file(path: str | Path, what: str, fix: str, map_location: str | torch.device = "cpu"):
    """torch.load(path, weights_only=True) of a regular file, every failure a CheckpointError
    naming `path`, `what` was expected and the `fix`."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: no such file; expected a {what}. {fix}")
    if path.is_dir():
        inside = sorted(path.rglob("*.ckpt"))[:3]
        hint = f" (it holds e.g. {', '.join(map(str, inside))})" if inside else ""
        raise CheckpointError(f"{path} is a folder, not a {what}{hint}. {fix}")
    if not path.is_file():  # a FIFO or a device would block or never end
        raise CheckpointError(f"{path} is not a regular file; expected a {what}. {fix}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch.load raises many types for foreign bytes; each is a bad file here
        message = str(e)
        if "WeightsUnpickler error:" in message:  # the useful part of torch's long explanation
            message = message.split("WeightsUnpickler error:", 1)[1]
        lines = [line.strip() for line in message.splitlines() if line.strip()]
        detail = lines[0].split(". ")[0][:200] if lines else type(e).__name__
        if "Unsupported global" in message:
            found = (
                f"it holds objects other than tensors and plain containers ({detail}), which this package "
                "never "
                "unpickles (they could run code)"
            )
        elif "central directory" in str(e) or "zip archive" in str(e) or isinstance(e, EOFError):
            found = (
                f"it is truncated or damaged ({detail}); copy or download it again, or use the run's other "
                "checkpoint (last.ckpt/best.ckpt)"
            )
        else:
            found = f"it is not a PyTorch checkpoint at all ({type(e).__name__}: {detail})"
        raise CheckpointError(f"{path} is not a {what}: {found}. {fix}") from None


def load_checkpoint(
    path: str | Path,
    kind: str | None,
    expected_fingerprint: str | None = None,
    map_location: str | torch.device = "cpu",
) -> dict:
    """The checkpoint dict at `path`, checked: readable with weights_only=True, of `kind`
    (CHECKPOINTS; None: any of them), and with weights whose fingerprint is the one recorded in it at
    save time (when recorded) and `expected_fingerprint` (when given). CheckpointError otherwise."""
    what, make = CHECKPOINTS[kind] if kind else ("checkpoint of this package", "")
    fix = (
        f"Give the path of a {what}; {make}."
        if kind
        else "Give the path of a checkpoint written by this package's training."
    )
    ckpt = read_torch_file(path, what, fix, map_location)
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path} is not a {what}: it holds a {type(ckpt).__name__}, not a dict. {fix}")
    found = checkpoint_kind(ckpt)
    if found is None:
        raise CheckpointError(f"{path} is not a {what}: it holds {_describe(ckpt)}. {fix}")
    if kind is not None and found != kind:
        raise CheckpointError(
            f"{path} is a {CHECKPOINTS[found][0]}, not a {what}; pass it {_PASSED_AS[found]}. {fix}"
        )
    recorded = ckpt.get(FINGERPRINT_KEY)
    if recorded is not None or expected_fingerprint is not None:
        actual = weights_fingerprint(ckpt)
        for expected, source in (
            (recorded, "recorded in the file when it was saved"),
            (expected_fingerprint, "expected by the registry"),
        ):
            if expected is not None and actual != expected:
                raise CheckpointError(
                    f"{path}: its weights have fingerprint {actual}, but {expected} was {source}; the file "
                    "was changed or damaged "
                    "after it was written. Use an intact copy (download it again, or the run's own "
                    "checkpoints/best.ckpt)."
                )
    return ckpt


def load_state(module: torch.nn.Module, state: dict, path: str | Path, kind: str) -> None:
    """module.load_state_dict(state), a mismatch (missing, unexpected or mis-shaped weights) a
    CheckpointError."""
    try:
        module.load_state_dict(state)
    except (RuntimeError, KeyError, ValueError) as e:
        detail = str(e).strip().splitlines()[0][:300]
        raise CheckpointError(
            f"{path}: its weights do not fit the {CHECKPOINTS[kind][0]} its hyper-parameters describe "
            f"({detail}); the file was edited or "
            f"mixed from two models. Use the checkpoint as training wrote it."
        ) from None


def trusted_recorded_path(recorded: str | Path | None) -> Path | None:
    """A file path recorded in a checkpoint, when it may be followed without the user naming it:
    an existing regular file inside `outputs/` of the working directory (symbolic links resolved
    first). None when nothing is recorded or the file is not there."""
    if not recorded:
        return None
    path = Path(recorded)
    if not path.is_file():
        return None
    if not path.resolve().is_relative_to(Path(OUTPUTS_ROOT).resolve()):
        return None
    return path


def outside_outputs(recorded: str | Path | None) -> bool:
    """True for a recorded path that exists but lies outside `outputs/` (refused unless passed)."""
    return (
        bool(recorded)
        and Path(recorded).exists()
        and not Path(recorded).resolve().is_relative_to(Path(OUTPUTS_ROOT).resolve())
    )


# Text-encoder options a checkpoint records (text/encoders.py TextConfig.options()).
TEXT_FILE_OPTIONS = {
    "weights": "--clip-weights",
    "vocab": "--clip-vocab",
}  # option -> the CLI flag that passes it
TEXT_PLAIN_OPTIONS = ("activation", "precision", "words")


def text_encoder_options(recorded: dict, given: dict | None, source: str | Path) -> tuple[str, dict]:
    """(name, options) that build the text encoder a checkpoint at `source` was trained with.

    The name and the plain options (activation, precision, words) come from the record; the
    options naming files (CLIP's weights and vocab) from `given` (named by the user, or the files
    a registry bundle carries), else from the record only when `trusted_recorded_path` allows it.
    A recorded file elsewhere, or any other recorded option, is a CheckpointError saying how to
    pass the file. The caller checks the built encoder's identity against the recorded one.
    """
    recorded = dict(recorded or {})
    name = recorded.get("name")
    if not name:
        raise CheckpointError(
            f"{source}: records no text encoder; it was not written by this package's training"
        )
    given = {k: str(v) for k, v in (given or {}).items() if v is not None}
    unknown = sorted(set(given) - set(TEXT_FILE_OPTIONS))
    if unknown:
        raise ValueError(
            f"text-encoder files {', '.join(unknown)} are not options of a text encoder; give "
            f"{', '.join(TEXT_FILE_OPTIONS)}"
        )
    options: dict = {}
    for key, value in recorded.items():
        if key in ("name", "identity") or value is None:
            continue
        if key in TEXT_PLAIN_OPTIONS:
            options[key] = value
        elif key in TEXT_FILE_OPTIONS:
            if key in given:
                continue
            trusted = trusted_recorded_path(value)
            if trusted is None:
                where = "outside outputs/" if Path(value).exists() else "not on this machine"
                raise CheckpointError(
                    f"{source}: its text encoder {name} was trained with the {key} file {value}, which is "
                    f"{where}; a file a checkpoint "
                    f"names is read only from outputs/ or when you name it: pass {TEXT_FILE_OPTIONS[key]} "
                    "PATH "
                    f"(from Python: text_files={{'{key}': PATH}}). The encoder's fingerprint is checked "
                    "either way."
                )
            options[key] = str(trusted)
        else:
            raise CheckpointError(
                f"{source}: records the text-encoder option {key}={value!r}, which is never taken from a "
                "checkpoint "
                f"(only {', '.join(TEXT_PLAIN_OPTIONS)} and the files {', '.join(TEXT_FILE_OPTIONS)}); use a "
                "checkpoint written by this package's training"
            )
    options.update(given)
    return name, options

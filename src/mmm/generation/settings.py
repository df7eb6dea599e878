"""What a generation call may be given, and the allowed values: the sampling settings
(SamplingConfig, used by mmm.generation.sampler), the precision of the decoding passes
(mmm.generation.precision), seeds and counts. The CLI and the pyfunc bundle both check their
inputs here, so the two accept exactly the same values; nothing here imports torch, so the CLI
refuses a bad flag before a model's libraries load."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

from mmm.transformer.schedules import DECODING_SCHEDULES, check_schedule

DECODINGS = ("package", "released")

# The allowed ranges of the sampling settings and of the per-request counts.
MAX_ITERATIONS = 100  # T_max: the paper's grid ends at 30; more passes only cost time
MIN_TEMPERATURE = 1e-3  # a positive temperature below this is greedy decoding in all but name
MAX_TEMPERATURE = 100.0  # far past uniform sampling already
MAX_GUIDANCE = 100.0  # larger scales only push the logits towards float overflow
MAX_SEED = 2**63 - 1  # torch generators take 64 bits; one sign bit kept free so every tool agrees
MAX_SAMPLES = 64  # samples of one command, rows of one served request (its default bound)
MAX_CANDIDATES = 16  # best of N: motions drawn per prompt (mmm.generation.best_of)

PRECISIONS = ("fp32", "bf16", "int8")
# The precision when none is asked for (benchmarks/inference_precision.py, README "Speed"): on CPU
# int8, the fastest at every case measured (4x float32 at the paper size), with prompt adherence
# and FID within float32's intervals on the demo model; float32 on a GPU: int8 is CPU-only, and bf16
# on an H200 was slower than float32 at batch 1 (AITS 82 against 62 ms: a batch-1 pass is bound by
# kernel launches, and autocast adds cast kernels), faster only for large batches (README "Speed on
# a GPU"). The release's codes are reproduced in fp32 only.
DEFAULT_PRECISION = {"cpu": "int8", "cuda": "fp32"}


def check_precision(precision: str) -> str:
    """`precision` when it is one of PRECISIONS, else a ValueError naming the choices."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    return precision


class SamplingValueError(ValueError):
    """A sampling setting (or a seed or a count) outside its allowed range.

    `field` is the setting's name here (max_iterations, temperature, ...), so that a caller can
    name it its own way (the CLI's --iterations, a request's params)."""

    def __init__(self, field: str, value, allowed: str):
        self.field, self.value, self.allowed = field, value, allowed
        super().__init__(f"{field} {value!r} is not allowed: {allowed}")


def _check_number(field: str, value, low: float, high: float, allowed: str) -> None:
    """SamplingValueError unless value is a finite real number (not a bool) in [low, high]."""
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not math.isfinite(value)
        or not low <= value <= high
    ):
        raise SamplingValueError(field, value, allowed)


def _check_integer(field: str, value, low: int, high: int, allowed: str) -> None:
    """SamplingValueError unless value is an int (not a bool) in [low, high]."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not low <= value <= high:
        raise SamplingValueError(field, value, allowed)


def check_seed(seed, field: str = "seed") -> int:
    """The seed as an int in 0..2^63-1, or SamplingValueError."""
    _check_integer(field, seed, 0, MAX_SEED, f"an integer from 0 to 2^63-1 ({MAX_SEED})")
    return int(seed)


def check_count(count, field: str, limit: int = MAX_SAMPLES) -> int:
    """A number of samples (or rows) in 1..limit, or SamplingValueError."""
    _check_integer(field, count, 1, limit, f"an integer from 1 to {limit}")
    return int(count)


def check_candidates(candidates, field: str = "candidates") -> int:
    """A number of motions drawn per prompt (best of N) in 1..MAX_CANDIDATES, or SamplingValueError."""
    _check_integer(
        field,
        candidates,
        1,
        MAX_CANDIDATES,
        f"a whole number of motions drawn per prompt, 1 to {MAX_CANDIDATES} (1: no judge; from text, 4 at "
        "guidance 1.5 follows the most prompts, README 'Best of N')",
    )
    return int(candidates)


@dataclass
class SamplingConfig:
    """Each field's metadata describes its command-line option (the CLI builds its sampling flags
    from these fields): "flag" where the option is not --<field-name> (None: not on the command
    line), "help" its help text, "choices" its allowed values."""

    # T_max
    max_iterations: int = field(
        default=10, metadata={"flag": "--iterations", "help": "T_max (each sample runs ceil(T_max * L / 50))"}
    )
    # a name of transformer/schedules.py DECODING_SCHEDULES
    schedule: str = field(default="cosine", metadata={"choices": tuple(DECODING_SCHEDULES)})
    temperature: float = 1.0  # 0: always the most likely code
    # keep this fraction of the codebook's logits (1.0 = all)
    top_k: float | None = field(default=None, metadata={"help": "fraction of the codebook kept, e.g. 0.9"})
    top_p: float | None = None  # nucleus: the smallest set of codes with this total probability
    # 1: conditional only; > 1 needs a model trained with cond_drop
    guidance_scale: float = field(
        default=1.0,
        metadata={
            "flag": "--guidance",
            "help": "classifier-free guidance scale (1: none; default 1, 4 for upper-body edits)",
        },
    )
    # False: every sample runs max_iterations
    dynamic_iterations: bool = field(default=True, metadata={"flag": None})
    # package (mmm.generation.sampler's rule) | released (the authors' loop: the sampler's docstring)
    decoding: str = field(
        default="package",
        metadata={
            "choices": DECODINGS,
            "help": "released: the authors' decoding loop (to compare outputs and speed with imported "
            "weights "
            "like for like)",
        },
    )

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        """ValueError naming the field, its value and the allowed range (SamplingValueError for a
        value out of range): NaN and infinities never reach the decoder, whose softmax and
        draw would fail on them mid-generation."""
        if self.decoding not in DECODINGS:
            raise ValueError(f"decoding must be one of {', '.join(DECODINGS)}, got {self.decoding!r}")
        check_schedule(self.schedule, DECODING_SCHEDULES, "schedule")
        _check_integer(
            "max_iterations", self.max_iterations, 1, MAX_ITERATIONS, f"an integer from 1 to {MAX_ITERATIONS}"
        )
        if self.temperature != 0:
            _check_number(
                "temperature",
                self.temperature,
                MIN_TEMPERATURE,
                MAX_TEMPERATURE,
                f"0 (always the most likely code) or a number from {MIN_TEMPERATURE:g} to "
                f"{MAX_TEMPERATURE:g}",
            )
        _check_number(
            "guidance_scale",
            self.guidance_scale,
            0.0,
            MAX_GUIDANCE,
            f"a number from 0 to {MAX_GUIDANCE:g} (1: no guidance)",
        )
        if self.top_k is not None and not (isinstance(self.top_k, numbers.Real) and 0.0 < self.top_k <= 1.0):
            raise SamplingValueError(
                "top_k", self.top_k, "a fraction of the codebook in (0, 1] (1: all codes)"
            )
        if self.top_p is not None and not (isinstance(self.top_p, numbers.Real) and 0.0 < self.top_p <= 1.0):
            raise SamplingValueError("top_p", self.top_p, "a total probability in (0, 1] (1: all codes)")
        if self.decoding == "released":
            unsupported = [
                f"{name}={value}"
                for name, value, default in (
                    ("schedule", self.schedule, "cosine"),
                    ("top_k", self.top_k, None),
                    ("top_p", self.top_p, None),
                    ("guidance_scale", self.guidance_scale, 1.0),
                )
                if value != default
            ]
            if unsupported:
                raise ValueError(
                    "the released decoding has a cosine schedule and no top-k, top-p or guidance; drop "
                    f"{', '.join(unsupported)} "
                    "or use decoding=package"
                )

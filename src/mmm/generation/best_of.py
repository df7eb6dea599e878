"""Best of N: draw several motions per prompt and keep the one a text-motion judge puts closest to it.

The judge is the package's contrastive evaluator (mmm.evaluation.contrastive), trained on the same
data: it embeds a caption and a motion in one space, and their cosine says how well the motion does
what the text says. The N candidates of every prompt are decoded in one batch, so a call costs
about N times the decoding of one sample, plus one pass of the judge.

Edits (`edit_best_of`) draw N edits of the source and judge only the frames the edit generated;
long sequences (`generate_long_best_of`) pick each prompt's segment before the transitions join them.

Why: one draw of the sampler often misses a detail its next draw gets right (the second action of
"walks, then jumps", the third of "jumps three times"); the judge sees the difference. More
candidates are not better without end: the maximum over many draws finds motions the judge rates
above what they do (README, "Best of N").
"""

from __future__ import annotations

import time

import numpy as np
import torch
import torch.nn.functional as F

from mmm.generation.model import Generated, TextToMotion
from mmm.generation.sampler import SamplingConfig
from mmm.motion.features import pad_motions

MAX_CANDIDATES = 16


def check_candidates(candidates: int, name: str = "candidates") -> int:
    if (
        isinstance(candidates, bool)
        or not isinstance(candidates, int)
        or not 1 <= candidates <= MAX_CANDIDATES
    ):
        raise ValueError(
            f"{name} {candidates!r} is not allowed: a whole number of motions drawn per prompt, "
            f"1 to {MAX_CANDIDATES} (1: no judge; from text, 4 at guidance 1.5 follows the most prompts, "
            "README 'Best of N')"
        )
    return candidates


def check_judge(model: TextToMotion, judge) -> None:
    """Refuse a judge that cannot read this model's motions: another feature layout, or no caption
    strings (the standard T2M evaluator needs tagged captions)."""
    if not hasattr(judge, "sentence_embeddings"):
        raise ValueError(
            f"the judge {getattr(judge, 'identity', type(judge).__name__)} does not embed caption strings; "
            "best of N needs the package's own evaluator (`make train-evaluator`, or a path, run id or "
            "models:/mmm-evaluator@champion)"
        )
    dim = (getattr(judge, "info", None) or {}).get("feature_dim")
    if dim is not None and int(dim) != model.feature_dim:
        raise ValueError(
            f"the judge was trained on {dim}-dimensional motion features but the model makes "
            f"{model.feature_dim}; use an evaluator trained on the model's dataset"
        )


@torch.no_grad()
def judge_scores(judge, texts: list[str], features: list[np.ndarray]) -> np.ndarray:
    """Cosine (B,) of each text with its motion (un-normalized (T_i, D)) in the judge's space
    (for an edit, what `edited_span` cuts out)."""
    lengths = [len(f) for f in features]
    batch = pad_motions(features)
    unique = {t: i for i, t in enumerate(dict.fromkeys(texts))}  # each distinct text embedded once
    text = F.normalize(judge.embed_texts(list(unique)).float(), dim=-1)
    text = text[torch.tensor([unique[t] for t in texts])]
    motion = F.normalize(judge.embed_motions(batch, lengths).float(), dim=-1).to(text.device)
    return (text * motion).sum(-1).cpu().numpy()


def _keep_best(drawn: Generated, scores: np.ndarray, seconds: dict) -> Generated:
    """Each row's best candidate of `drawn` (candidate-major rows, scores (n, candidates)); kept
    codes with a row per draw (upper-body edits) keep the chosen rows'."""
    n = len(scores)
    rows = [int(k) * n + i for i, k in enumerate(scores.argmax(1))]
    kept = drawn.kept_codes
    if kept is not None and np.ndim(kept) == 2:
        kept = kept[rows]
    return Generated(
        [drawn.texts[r] for r in rows],
        [drawn.features[r] for r in rows],
        [drawn.joints[r] for r in rows],
        [drawn.codes[r] for r in rows],
        [drawn.iterations[r] for r in rows],
        drawn.forward_passes,
        seconds,
        kept_codes=kept,
        scores=scores,
    )


def generate_best_of(
    model: TextToMotion,
    judge,
    texts: list[str],
    frames: list[int] | None = None,
    candidates: int = 4,
    sampling: SamplingConfig | None = None,
    seed: int | None = None,
    check_lengths: bool = True,
) -> Generated:
    """One motion per text (as `model.generate`), the best of `candidates` by the judge's cosine.

    The candidates of a text share its length (estimated once when `frames` is None). The result's
    `scores` (B, candidates) holds every candidate's cosine; the kept one is each row's maximum.
    candidates=1 is `model.generate` with the scores added."""
    check_candidates(candidates)
    check_judge(model, judge)
    started = time.perf_counter()
    frames = list(frames) if frames is not None else model.estimate_frames(texts)
    if len(frames) != len(texts):
        raise ValueError(f"{len(texts)} texts but {len(frames)} lengths")
    n = len(texts)
    # Candidate-major rows: row k * n + i is candidate k of text i.
    drawn = model.generate(
        texts * candidates, frames * candidates, sampling, seed, check_lengths=check_lengths
    )
    t0 = time.perf_counter()
    scores = judge_scores(judge, texts * candidates, drawn.features).reshape(candidates, n).T
    seconds = {**drawn.seconds, "judge": time.perf_counter() - t0}
    seconds["total"] = time.perf_counter() - started
    return _keep_best(drawn, scores, seconds)


MIN_JUDGED_FRAMES = 16  # shorter edited spans are judged on the whole motion


def edited_span(kept_codes: np.ndarray | None, frames: int, unit: int) -> tuple[int, int]:
    """Frames [start, end) an edit generated: from its first to its last code not kept from the
    source (kept_codes (L,) bool); the whole motion for an upper-body edit (kept_codes None or 2-D:
    every frame is new above the hips) or a span under MIN_JUDGED_FRAMES."""
    if kept_codes is None or np.ndim(kept_codes) != 1 or np.all(kept_codes):
        return 0, frames
    new = np.flatnonzero(~np.asarray(kept_codes, dtype=bool))
    start, end = int(new[0]) * unit, min(int(new[-1] + 1) * unit, frames)
    return (start, end) if end - start >= MIN_JUDGED_FRAMES else (0, frames)


def edit_best_of(
    request,
    model: TextToMotion,
    judge,
    source: np.ndarray,
    candidates: int = 4,
    sampling: SamplingConfig | None = None,
    seed: int | None = None,
    num_samples: int = 1,
) -> tuple[Generated, tuple[int, int]]:
    """An edit (mmm.generation.edits.EditRequest) as best of `candidates`: every sample the draw
    whose edited frames (`edited_span`) the judge puts closest to the request's text. Returns the
    result (scores (num_samples, candidates)) and the span judged. An edit without text has
    nothing to judge against and is refused."""
    check_candidates(candidates)
    check_judge(model, judge)
    if not request.text:
        raise ValueError(
            f"best of N judges the edited part against its text: give {request.kind} a text, or draw one "
            "candidate"
        )
    started = time.perf_counter()
    drawn = request.run(model, source, sampling, seed, num_samples * candidates)
    t0 = time.perf_counter()
    start, end = edited_span(drawn.kept_codes, len(drawn.features[0]), model.unit)
    spans = [f[start:end] for f in drawn.features]
    scores = judge_scores(judge, [request.text] * len(spans), spans).reshape(candidates, num_samples).T
    seconds = {**drawn.seconds, "judge": time.perf_counter() - t0}
    seconds["total"] = time.perf_counter() - started
    return _keep_best(drawn, scores, seconds), (start, end)


def generate_long_best_of(
    model: TextToMotion,
    judge,
    texts: list[str],
    frames: list[int] | None = None,
    candidates: int = 4,
    sampling: SamplingConfig | None = None,
    seed: int | None = None,
    transition_codes: int = 2,
) -> Generated:
    """`model.generate_long` with each prompt's segment the best of `candidates` by the judge; the
    transitions are drawn between the kept segments. `scores` (prompts, candidates)."""
    segments = generate_best_of(model, judge, texts, frames, candidates, sampling, seed)
    out = model.generate_long(texts, None, sampling, seed, transition_codes, segments=segments)
    out.seconds = {**out.seconds, "segments": segments.seconds["total"]}
    out.seconds["total"] += segments.seconds["total"]
    return out

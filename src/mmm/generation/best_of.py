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

A caption in two steps ("walks forward and then jumps", "..., followed by ...") is also judged
clause by clause (`caption_clauses`, `clause_scores`): the first clause against the motion up to a
cut, the second after it, at the cut that fits best. One embedding of the whole clip weighs the
second action lightly, and that is the action a draw most often misses.

A caption with a count or speed word ("jumps twice", "walks slowly") is also judged against its
counterfactuals, the same caption with that word changed (`counterfactual_margins`): a draw gains
by how much better the judge reads it as the caption than as "jumps three times". The cosine alone
trades the count or speed for how clearly the action is done; the margin asks the judge about the
word itself. Measured, it picks better on speeds and no better on counts (README, "Best of N").
"""

from __future__ import annotations

import math
import re
import time

import numpy as np
import torch
import torch.nn.functional as F

from mmm.generation.model import Generated, TextToMotion
from mmm.generation.settings import SamplingConfig, check_candidates
from mmm.motion.features import pad_motions
from mmm.text.counterfactuals import counterfactual_captions


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


def _text_embeddings(judge, texts: list[str]) -> torch.Tensor:
    """(B, E) unit embeddings of the texts, each distinct text through the judge once."""
    unique = {t: i for i, t in enumerate(dict.fromkeys(texts))}
    text = F.normalize(judge.embed_texts(list(unique)).float(), dim=-1)
    return text[torch.tensor([unique[t] for t in texts])]


def _motion_embeddings(judge, features: list[np.ndarray]) -> torch.Tensor:
    """(B, E) unit embeddings of the motions (un-normalized (T_i, D))."""
    motion = judge.embed_motions(pad_motions(features), [len(f) for f in features])
    return F.normalize(motion.float(), dim=-1)


def _cosines(text: torch.Tensor, motions: torch.Tensor) -> np.ndarray:
    """Cosine (B,) of each unit text embedding (B, E) with its unit motion embedding (B, E)."""
    return (text.to(motions.device) * motions).sum(-1).cpu().numpy()


# Words that put one action after another. "and" alone is left out: it also joins actions done at
# once ("walks and waves").
_SEQUENCE = re.compile(
    r"\s*,?\s*\b(?:(?:and\s+)?(?:then|afterwards|after\s+that)|followed\s+by)\b\s*,?\s*", re.IGNORECASE
)
_FIRST = re.compile(r"\bfirst\b,?\s*", re.IGNORECASE)


def caption_clauses(text: str) -> tuple[str, str] | None:
    """The two steps of a caption that says one thing happens after another ("a person walks
    forward and then jumps" -> ("a person walks forward", "jumps")), "first" dropped from the
    first; None for a caption in one step or in more than two."""
    parts = _SEQUENCE.split(text)
    if len(parts) != 2:
        return None
    first, second = (part.strip(" .,;") for part in (_FIRST.sub("", parts[0]), parts[1]))
    return (first, second) if first and second else None


CLAUSE_CUT_STEP = 8  # frames between the cuts tried (two codes)
# The shortest piece a clause is judged on: a quarter of the motion, and at least 16 frames. Each
# cut costs two passes of the judge over pieces as long as the motion, so the cuts are kept few.
CLAUSE_MIN_FRAMES = 16
CLAUSE_MIN_SHARE = 0.25
CLAUSE_BATCH = 256  # pieces embedded at once


@torch.no_grad()
def clause_scores(judge, texts: list[str], features: list[np.ndarray]) -> np.ndarray:
    """(B,) for captions in two steps (`caption_clauses`): the best, over cuts every
    CLAUSE_CUT_STEP frames leaving a quarter of the motion and at least CLAUSE_MIN_FRAMES on each
    side, of the mean of the first clause's cosine with the motion before the cut and the
    second's with the rest; NaN for other captions and for motions too short to cut."""
    out = np.full(len(texts), np.nan)
    pieces, clause_texts, owner = [], [], []  # owner: (row, cut index, which half)
    cuts_of: dict[int, int] = {}
    for row, (text, motion) in enumerate(zip(texts, features)):
        clauses = caption_clauses(text)
        shortest = max(CLAUSE_MIN_FRAMES, math.ceil(CLAUSE_MIN_SHARE * len(motion)))
        cuts = range(shortest, len(motion) - shortest + 1, CLAUSE_CUT_STEP)
        if clauses is None or not cuts:
            continue
        cuts_of[row] = len(cuts)
        for c, cut in enumerate(cuts):
            for half, (piece, clause) in enumerate(((motion[:cut], clauses[0]), (motion[cut:], clauses[1]))):
                pieces.append(piece)
                clause_texts.append(clause)
                owner.append((row, c, half))
    if not pieces:
        return out
    # In slices of similar lengths: a draw of 196 frames makes 26 pieces, an evaluation batch's
    # pieces padded together would take hundreds of MB, and the judge's GRUs run over the padding.
    text = _text_embeddings(judge, clause_texts)
    order = np.argsort([len(piece) for piece in pieces], kind="stable")
    cosines = np.empty(len(pieces))
    for i in range(0, len(order), CLAUSE_BATCH):
        rows = order[i : i + CLAUSE_BATCH]
        motions = _motion_embeddings(judge, [pieces[r] for r in rows])
        cosines[rows] = _cosines(text[torch.from_numpy(rows)], motions)
    per_cut = {row: np.zeros((n, 2)) for row, n in cuts_of.items()}
    for (row, c, half), value in zip(owner, cosines):
        per_cut[row][c, half] = value
    for row, values in per_cut.items():
        out[row] = values.mean(1).max()
    return out


# How much the margin over the nearest counterfactual weighs beside the caption's own score
# (chosen on the validation draws: README, "Best of N", counterfactual margins).
COUNTERFACTUAL_WEIGHT = 0.25


@torch.no_grad()
def counterfactual_margins(judge, texts: list[str], motions: torch.Tensor, cosines: np.ndarray) -> np.ndarray:
    """(B,) for a caption with a count or speed word: its cosine with the motion (`cosines` (B,),
    of the unit embeddings `motions` (B, E)) minus the highest cosine of its counterfactuals
    (mmm.text.counterfactuals: "jumps twice" against "jumps once", "... three times", "...
    four times"); NaN for other captions. Positive when the judge reads the motion as this caption
    rather than as any of its one-word changes."""
    out = np.full(len(texts), np.nan)
    variants = {t: counterfactual_captions(t) for t in dict.fromkeys(texts)}
    wordings = list(dict.fromkeys(v for vs in variants.values() for v in vs))
    if not wordings:
        return out
    embedded = dict(zip(wordings, _text_embeddings(judge, wordings).to(motions.device)))
    for row, text in enumerate(texts):
        if variants[text]:
            out[row] = cosines[row] - max(float(embedded[v] @ motions[row]) for v in variants[text])
    return out


@torch.no_grad()
def judge_scores(
    judge, texts: list[str], features: list[np.ndarray], by_clause: bool = True, counterfactuals: bool = True
) -> np.ndarray:
    """The judge's score (B,) of each text with its motion (un-normalized (T_i, D); for an edit,
    what `edited_span` cuts out): the cosine of their embeddings; for a caption in two steps (with
    by_clause) the mean of that and its `clause_scores`; for a caption with a count or speed word
    (with counterfactuals) plus COUNTERFACTUAL_WEIGHT times its `counterfactual_margins`. Only the
    order of a caption's scores matters: the cosine is in [-1, 1], the margin in [-2, 2]."""
    motions = _motion_embeddings(judge, features)
    cosine = _cosines(_text_embeddings(judge, texts), motions)
    score = cosine
    if by_clause:
        clauses = clause_scores(judge, texts, features)
        score = np.where(np.isnan(clauses), score, (score + clauses) / 2)
    if counterfactuals:
        margins = counterfactual_margins(judge, texts, motions, cosine)
        score = np.where(np.isnan(margins), score, score + COUNTERFACTUAL_WEIGHT * margins)
    return score


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
    by_clause: bool = True,
    counterfactuals: bool = True,
) -> Generated:
    """One motion per text (as `model.generate`), the best of `candidates` by the judge's score
    (`judge_scores`; by_clause=False and counterfactuals=False: the whole caption's cosine only).

    The candidates of a text share its length (estimated once when `frames` is None). The result's
    `scores` (B, candidates) holds every candidate's score; the kept one is each row's maximum.
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
    scores = judge_scores(judge, texts * candidates, drawn.features, by_clause, counterfactuals)
    scores = scores.reshape(candidates, n).T
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

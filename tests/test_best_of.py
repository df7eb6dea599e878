"""Best of N (mmm.generation.best_of): the judge's choice among candidates, and what it refuses."""

import numpy as np
import pytest
import torch

from mmm.generation.best_of import (
    COUNTERFACTUAL_WEIGHT,
    MIN_JUDGED_FRAMES,
    caption_clauses,
    check_judge,
    clause_scores,
    counterfactual_margins,
    edit_best_of,
    edited_span,
    generate_best_of,
    generate_long_best_of,
    judge_scores,
)
from mmm.generation.model import Generated
from mmm.generation.settings import check_candidates


class Draws:
    """Candidate motions whose every frame holds the draw's number: row r of a call is filled with
    `values[r]` (a stand-in for the sampler's randomness), so the judge's choice can be read back."""

    feature_dim = 3

    def __init__(self, values):
        self.values, self.calls = values, []

    def estimate_frames(self, texts):
        return [40 + 4 * len(t) for t in texts]

    def generate(self, texts, frames, sampling=None, seed=None, check_lengths=True):
        self.calls.append((list(texts), list(frames)))
        features = [np.full((n, 3), self.values[r], np.float32) for r, n in enumerate(frames)]
        codes = [np.full(n // 4, r) for r, n in enumerate(frames)]
        return Generated(list(texts), features, [f[:, None] for f in features], codes, [1] * len(texts), 1)


class ValueJudge:
    """Texts embed as (1, 0); a motion as (cos a, sin a) with a = |its value - the text's target|,
    so the candidate nearest each text's target value has the highest cosine."""

    info = {"feature_dim": 3}
    identity = "value-judge"

    def __init__(self, targets):
        self.targets = targets

    def sentence_embeddings(self, texts):
        raise AssertionError("not called: embed_texts is")

    def embed_texts(self, texts):
        self.texts = [*getattr(self, "texts", []), *texts]
        return torch.tensor([[1.0, 0.0]] * len(texts))

    def embed_motions(self, features, lengths):
        features = torch.as_tensor(features)
        value = torch.stack([features[i, : int(n)].mean() for i, n in enumerate(lengths)])
        # Padding past each length must not count: the mean above reads only the valid frames.
        target = torch.tensor([self.targets[i % len(self.targets)] for i in range(len(value))])
        angle = (value - target).abs()
        return torch.stack([angle.cos(), angle.sin()], -1)


def test_keeps_each_texts_candidate_the_judge_rates_highest():
    # Two texts, three candidates each; rows are candidate-major (k * 2 + i).
    values = [0.9, 0.0, 0.1, 0.5, 0.6, 1.4]
    model, judge = Draws(values), ValueJudge(targets=[0.5, 1.5])
    out = generate_best_of(model, judge, ["walk", "jump twice"], [40, 48], candidates=3, seed=0)
    ((texts, frames),) = model.calls
    assert texts == ["walk", "jump twice"] * 3 and frames == [40, 48] * 3  # one batch, lengths shared
    assert out.scores.shape == (2, 3)
    np.testing.assert_allclose(
        out.scores, np.cos(np.abs(np.array([[0.9, 0.1, 0.6], [0.0, 0.5, 1.4]]) - [[0.5], [1.5]])), atol=1e-6
    )
    # Nearest each target: 0.6 (candidate 2 of text 0, row 4) and 1.4 (candidate 2 of text 1, row 5).
    assert [float(f[0, 0]) for f in out.features] == [pytest.approx(0.6), pytest.approx(1.4)]
    assert [len(f) for f in out.features] == [40, 48]
    assert [int(c[0]) for c in out.codes] == [4, 5]  # the kept rows' own codes
    # Each distinct wording embedded once: the texts, then the count's counterfactuals (which tie
    # here: this judge reads no words).
    assert judge.texts == ["walk", "jump twice", "jump once", "jump three times", "jump four times"]
    assert "judge" in out.seconds and out.texts == ["walk", "jump twice"]


def test_one_candidate_is_the_plain_draw_and_lengths_are_estimated_once():
    model = Draws([0.3, 0.7])
    out = generate_best_of(model, ValueJudge([0.0]), ["a", "bb"], None, candidates=1)
    assert model.calls == [(["a", "bb"], [44, 48])]
    assert out.scores.shape == (2, 1) and [float(f[0, 0]) for f in out.features] == pytest.approx([0.3, 0.7])


def test_judge_scores_ignore_padding_past_each_length():
    judge = ValueJudge([0.0])
    short, long = np.full((8, 3), 0.2, np.float32), np.full((20, 3), 0.2, np.float32)
    np.testing.assert_allclose(judge_scores(judge, ["x", "x"], [short, long]), [np.cos(0.2)] * 2, atol=1e-6)


@pytest.mark.parametrize("bad", [0, 17, -1, 2.5, True, "4"])
def test_candidates_outside_one_to_sixteen_are_refused(bad):
    with pytest.raises(ValueError, match=r"--candidates .* is not allowed: .* 1 to 16"):
        check_candidates(bad, "--candidates")
    assert check_candidates(16) == 16


def test_a_judge_that_cannot_read_the_model_is_refused():
    model = Draws([0.0])

    class OtherLayout(ValueJudge):
        info = {"feature_dim": 251}

    with pytest.raises(ValueError, match="trained on 251-dimensional motion features but the model makes 3"):
        check_judge(model, OtherLayout([0.0]))

    class TaggedCaptionsOnly:
        identity = "t2m-evaluator"

    with pytest.raises(ValueError, match="t2m-evaluator does not embed caption strings"):
        generate_best_of(model, TaggedCaptionsOnly(), ["walk"], [40], candidates=2)
    assert model.calls == []  # refused before anything is drawn


class Edit:
    """A stand-in EditRequest: every draw keeps codes 0-4 and 15-19 of a 20-code (80-frame) motion,
    whose frames hold 9.0 there (the source), and fills the generated frames 20:60 with the draw's
    value. upper=True: an upper-body edit, kept_codes one row per draw."""

    def __init__(self, values, text="a person jumps", upper=False):
        self.values, self.text, self.upper, self.kind = values, text, upper, "inbetween"
        self.calls = []

    def run(self, model, source, sampling=None, seed=None, num_samples=1):
        self.calls.append(num_samples)
        features = []
        for r in range(num_samples):
            f = np.full((80, 3), 9.0, np.float32)
            f[20:60] = self.values[r]
            features.append(f)
        kept = np.zeros(20, bool)
        kept[:5] = kept[15:] = True
        if self.upper:
            kept = np.stack([np.full(20, r % 2 == 0) for r in range(num_samples)])
        codes = [np.full(20, r) for r in range(num_samples)]
        return Generated(
            [self.text] * num_samples,
            features,
            [f[:, None] for f in features],
            codes,
            [1] * num_samples,
            1,
            kept_codes=kept,
        )


class EditModel:
    feature_dim, unit = 3, 4


def test_edit_best_of_judges_the_edited_frames_only():
    # Two samples, three candidates (candidate-major rows k * 2 + i); the source frames (9.0) would
    # swamp every candidate's mean if they were judged.
    values = [0.9, 0.0, 0.1, 0.5, 0.6, 1.4]
    request = Edit(values)
    out, span = edit_best_of(request, EditModel(), ValueJudge([0.5]), None, candidates=3, num_samples=2)
    assert request.calls == [6] and span == (20, 60)
    assert out.scores.shape == (2, 3)
    expected = np.cos(np.abs(np.array([[0.9, 0.1, 0.6], [0.0, 0.5, 1.4]]) - 0.5))
    np.testing.assert_allclose(out.scores, expected, atol=1e-6)
    # Nearest 0.5: 0.6 for sample 0 (row 4), 0.5 for sample 1 (row 3).
    assert [float(f[40, 0]) for f in out.features] == [pytest.approx(0.6), pytest.approx(0.5)]
    assert [int(c[0]) for c in out.codes] == [4, 3] and out.kept_codes.shape == (20,)


def test_upper_body_edits_are_judged_whole_and_keep_their_rows_kept_codes():
    request = Edit([0.0, 5.0, 9.0, 1.0], upper=True)  # whole motions: mean 9.0 * 0.5 + value * 0.5
    out, span = edit_best_of(request, EditModel(), ValueJudge([9.0]), None, candidates=2, num_samples=2)
    assert span == (0, 80)
    # Sample 0: rows 0 (0.0) and 2 (9.0) -> row 2; sample 1: rows 1 (5.0) and 3 (1.0) -> row 1.
    assert [int(c[0]) for c in out.codes] == [2, 1]
    assert out.kept_codes.tolist() == [[True] * 20, [False] * 20]  # rows 2 and 1 of the draws


def test_edited_span_and_what_edits_best_of_refuses():
    kept = np.array([True] * 5 + [False] * 10 + [True] * 5)
    assert edited_span(kept, 80, 4) == (20, 60)
    assert edited_span(np.array([False] * 10 + [True] * 10), 80, 4) == (0, 40)  # complete: the start new
    assert edited_span(kept, 58, 4) == (20, 58)  # never past the motion
    short = np.array([True] * 9 + [False] * 2 + [True] * 9)  # 8 frames < MIN_JUDGED_FRAMES
    assert MIN_JUDGED_FRAMES == 16 and edited_span(short, 80, 4) == (0, 80)
    assert edited_span(np.ones(20, bool), 80, 4) == (0, 80) and edited_span(None, 80, 4) == (0, 80)
    with pytest.raises(ValueError, match="judges the edited part against its text"):
        edit_best_of(Edit([0.0], text=None), EditModel(), ValueJudge([0.0]), None, candidates=2)
    with pytest.raises(ValueError, match="candidates 0 is not allowed"):
        edit_best_of(Edit([0.0]), EditModel(), ValueJudge([0.0]), None, candidates=0)


class LongDraws(Draws):
    """Draws whose generate_long joins the segments it is given (a stand-in for the transitions)."""

    def generate_long(self, texts, frames, sampling=None, seed=None, transition_codes=2, segments=None):
        self.long_call = (list(texts), frames, transition_codes)
        features = np.concatenate(segments.features)
        return Generated(
            [" / ".join(texts)],
            [features],
            [features[:, None]],
            [np.concatenate(segments.codes)],
            [1],
            1,
            {"total": 0.5},
            scores=segments.scores,
        )


def test_long_sequences_keep_each_prompts_best_segment():
    values = [0.9, 0.0, 0.1, 0.5, 0.6, 1.4]  # two prompts, three candidates, candidate-major
    model = LongDraws(values)
    out = generate_long_best_of(
        model, ValueJudge([0.5, 1.5]), ["walk", "jump"], [40, 48], 3, transition_codes=1
    )
    assert model.calls == [(["walk", "jump"] * 3, [40, 48] * 3)]  # every segment's candidates in one batch
    assert model.long_call == (["walk", "jump"], None, 1)
    # Segment 0: 0.6 nearest 0.5 (row 4); segment 1: 1.4 nearest 1.5 (row 5).
    assert out.features[0][:40, 0].tolist() == pytest.approx([0.6] * 40)
    assert out.features[0][40:, 0].tolist() == pytest.approx([1.4] * 48)
    assert out.scores.shape == (2, 3) and out.seconds["total"] > 0.5 and "segments" in out.seconds


@pytest.mark.parametrize(
    "caption, clauses",
    [
        ("a person walks forward and then jumps", ("a person walks forward", "jumps")),
        ("Someone first squats, then waves.", ("Someone squats", "waves")),
        ("a man runs, followed by a jump", ("a man runs", "a jump")),
        ("the person kicks and afterwards sits down", ("the person kicks", "sits down")),
        ("a person turns around. After that, they wave", ("a person turns around", "they wave")),
        ("a person walks and waves", None),  # "and" alone also joins actions done at once
        ("a person jumps twice", None),
        ("he strengthens his stance", None),  # "then" inside a word
        ("walks, then jumps, then sits", None),  # three steps
        ("then a person walks", None),  # nothing before the connective
    ],
)
def test_caption_clauses_splits_a_caption_in_two_steps_only(caption, clauses):
    assert caption_clauses(caption) == clauses


class ClauseJudge:
    """Texts embed by their words: "rises" as (1, 0), "falls" as (0, 1), both as (1, 1) / sqrt 2;
    a motion as (frames above 0, frames below 0) over its valid frames, so a piece's cosine with a
    clause is the share of the piece doing what the clause says."""

    info = {"feature_dim": 3}
    identity = "clause-judge"

    def sentence_embeddings(self, texts):
        raise AssertionError("not called: embed_texts is")

    def embed_texts(self, texts):
        return torch.tensor([[float("rises" in t), float("falls" in t)] for t in texts])

    def embed_motions(self, features, lengths):
        features = torch.as_tensor(features)
        rows = [features[i, : int(n), 0] for i, n in enumerate(lengths)]
        return torch.stack([torch.stack([(r > 0).sum(), (r < 0).sum()]).float() for r in rows])


def _rise_fall(first: float, frames: int = 96) -> np.ndarray:
    """(frames, 3): the first half at `first`, the second at `-first`."""
    half = np.full((frames // 2, 3), first, np.float32)
    return np.concatenate((half, -half))


def test_clause_scores_find_the_cut_and_tell_the_order_the_whole_caption_cannot():
    caption = "a thing rises and then falls"
    rise_fall, fall_rise = _rise_fall(1.0), _rise_fall(-1.0)
    judge = ClauseJudge()
    # 96 frames: cuts at 24, 32, ..., 72 (every 8, a quarter of the motion on each side).
    # Rise-then-fall: the cut at frame 48 gives each clause a piece it describes fully.
    # Fall-then-rise, by hand: the best cuts are 24 and 72 (the shortest first or last piece),
    # where one clause's piece is 24 of 72 frames right: cosine 24 / sqrt(48^2 + 24^2), the
    # other's 0.
    expected = 24 / np.hypot(48, 24) / 2
    np.testing.assert_allclose(
        clause_scores(judge, [caption] * 2, [rise_fall, fall_rise]), [1.0, expected], atol=1e-6
    )
    # The whole caption ("rises" and "falls": (1, 1)) scores both motions 1: half the frames each.
    np.testing.assert_allclose(
        judge_scores(judge, [caption] * 2, [rise_fall, fall_rise], by_clause=False), [1, 1], atol=1e-6
    )
    np.testing.assert_allclose(
        judge_scores(judge, [caption] * 2, [rise_fall, fall_rise]), [1.0, (1 + expected) / 2], atol=1e-6
    )
    # A caption in one step, or a motion too short to leave 16 frames on each side of a cut: no
    # clause score, the cosine alone.
    one_step, short = "a thing rises", _rise_fall(1.0, frames=30)
    assert np.isnan(clause_scores(judge, [one_step, caption], [rise_fall, short])).all()
    np.testing.assert_allclose(
        judge_scores(judge, [one_step, caption], [rise_fall, short]),
        judge_scores(judge, [one_step, caption], [rise_fall, short], by_clause=False),
    )


def test_best_of_keeps_the_draw_whose_steps_come_in_the_captions_order():
    class OrderedDraws(Draws):
        def generate(self, texts, frames, sampling=None, seed=None, check_lengths=True):
            features = [_rise_fall(self.values[r], n) for r, n in enumerate(frames)]
            codes = [np.full(n // 4, r) for r, n in enumerate(frames)]
            return Generated(
                list(texts), features, [f[:, None] for f in features], codes, [1] * len(texts), 1
            )

    model = OrderedDraws([-1.0, 1.0])  # candidate 0 falls first, candidate 1 rises first
    out = generate_best_of(model, ClauseJudge(), ["a thing rises, then falls"], [96], candidates=2)
    assert int(out.codes[0][0]) == 1 and out.scores[0, 1] == pytest.approx(1.0)
    whole = generate_best_of(
        model, ClauseJudge(), ["a thing rises, then falls"], [96], candidates=2, by_clause=False
    )
    np.testing.assert_allclose(whole.scores, [[1.0, 1.0]], atol=1e-6)  # a tie: the order is invisible to it


class CountJudge:
    """Texts embed as (1, cos 30n, sin 30n) for "n times" (n in 1-4, as words), (1, 0, 0) without a
    count; a motion whose frames hold (m, k, 0) as (m, cos 30k, sin 30k): how strongly it does
    the action, and how many times. The cosine then trades the count against the strength."""

    info = {"feature_dim": 3}
    identity = "count-judge"
    COUNTS = {"once": 1, "twice": 2, "three times": 3, "four times": 4}

    def sentence_embeddings(self, texts):
        raise AssertionError("not called: embed_texts is")

    def embed_texts(self, texts):
        rows = []
        for text in texts:
            n = next((n for word, n in self.COUNTS.items() if word in text), None)
            angle = np.radians(30 * n) if n else None
            rows.append([1.0, 0.0, 0.0] if n is None else [1.0, np.cos(angle), np.sin(angle)])
        return torch.tensor(rows, dtype=torch.float32)

    def embed_motions(self, features, lengths):
        features = torch.as_tensor(features)
        rows = []
        for i, n in enumerate(lengths):
            m, k = features[i, : int(n), :2].mean(0).tolist()
            angle = np.radians(30 * k)
            rows.append([m, np.cos(angle), np.sin(angle)])
        return torch.tensor(rows, dtype=torch.float32)


def test_counterfactual_margins_prefer_the_asked_count_to_a_closer_cosine():
    caption = "a person jumps twice"
    judge = CountJudge()
    asked = np.tile([0.4, 2.0, 0.0], (40, 1)).astype(np.float32)  # twice, done weakly
    other = np.tile([1.2, 3.0, 0.0], (40, 1)).astype(np.float32)  # three times, done strongly
    # By hand: cosine = (m + cos 30(n - k)) / (sqrt 2 * sqrt(m^2 + 1)).
    cos = lambda m, d: (m + np.cos(np.radians(30 * d))) / (np.sqrt(2) * np.hypot(m, 1))  # noqa: E731
    whole = judge_scores(judge, [caption] * 2, [asked, other], counterfactuals=False)
    np.testing.assert_allclose(whole, [cos(0.4, 0), cos(1.2, 1)], atol=1e-5)
    assert whole[1] > whole[0]  # the cosine alone prefers the strong three jumps
    # The variants are once, three times, four times. The asked draw beats its nearest (once or
    # three times: 30 degrees off); the other draw is read as "three times" better than as "twice".
    margins = [cos(0.4, 0) - cos(0.4, 1), cos(1.2, 1) - cos(1.2, 0)]
    motions = torch.nn.functional.normalize(judge.embed_motions(np.stack([asked, other]), [40, 40]), dim=-1)
    found = counterfactual_margins(judge, [caption] * 2, motions, whole)
    np.testing.assert_allclose(found, margins, atol=1e-5)
    # Cosines 0.919 and 0.935, margins +0.088 and -0.061: at the weight 0.25, 0.941 and 0.920.
    scores = judge_scores(judge, [caption] * 2, [asked, other])
    np.testing.assert_allclose(scores, whole + COUNTERFACTUAL_WEIGHT * np.array(margins), atol=1e-5)
    assert COUNTERFACTUAL_WEIGHT == 0.25 and scores == pytest.approx([0.9411, 0.9200], abs=1e-3)
    # Best of 2 keeps the asked count; without the counterfactuals, the other draw.
    model = Draws([0.0, 0.0])
    model.generate = lambda texts, frames, *a, **k: Generated(  # noqa: E731
        list(texts), [asked, other], [asked[:, None], other[:, None]], [np.zeros(10), np.ones(10)], [1, 1], 1
    )
    assert int(generate_best_of(model, judge, [caption], [40], candidates=2).codes[0][0]) == 0
    plain = generate_best_of(model, judge, [caption], [40], candidates=2, counterfactuals=False)
    assert int(plain.codes[0][0]) == 1
    # A caption without a count or speed word has no margin, and its score is the cosine.
    assert np.isnan(counterfactual_margins(judge, ["a person jumps"], motions[:1], whole[:1])).all()
    np.testing.assert_allclose(
        judge_scores(judge, ["a person jumps"], [asked]),
        judge_scores(judge, ["a person jumps"], [asked], counterfactuals=False),
    )

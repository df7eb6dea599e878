"""Counterfactual captions (a count or speed word changed), the hard-negative InfoNCE loss by hand,
the training collator's padding, and the ranking of a real motion's caption against its
counterfactuals with judges that can and cannot count."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from mmm.evaluation.contrastive_module import info_nce_loss
from mmm.evaluation.counterfactuals import counterfactual_ranking
from mmm.text import TextEmbedding
from mmm.text.counterfactuals import counterfactual_captions
from mmm.training.evaluator import CaptionedMotionCollator


@pytest.mark.parametrize(
    "caption, expected",
    [
        (
            "a person jumps twice",
            ["a person jumps once", "a person jumps three times", "a person jumps four times"],
        ),
        ("he squats 3 times", ["he squats once", "he squats 2 times", "he squats 4 times"]),
        ("Once, she claps", ["Twice, she claps", "Three times, she claps", "Four times, she claps"]),
        ("a man does three jumps ahead", ["a man does two jumps ahead", "a man does four jumps ahead"]),
        ("someone walks slowly", ["someone walks quickly"]),
        ("a fast run, then a slow walk", ["a slow run, then a slow walk", "a fast run, then a fast walk"]),
        (
            "she hops thrice quickly",
            [
                "she hops once quickly",
                "she hops twice quickly",
                "she hops four times quickly",
                "she hops thrice slowly",
            ],
        ),
        ("a person walks in a circle", []),  # nothing to count, no speed
        ("he jumps six times", []),  # above four: left alone
        ("the person moves breakfast", []),  # "fast" only as a whole word
    ],
)
def test_counterfactual_captions(caption, expected):
    assert counterfactual_captions(caption) == expected


def test_counterfactual_kinds_are_chosen_and_checked():
    caption = "a man jumps twice quickly"
    assert counterfactual_captions(caption, ("speed",)) == ["a man jumps twice slowly"]
    assert len(counterfactual_captions(caption, ("count",))) == 3
    assert counterfactual_captions(caption, ()) == []
    with pytest.raises(ValueError, match=r"\['colour'\] are not among \['count', 'speed'\]"):
        counterfactual_captions(caption, ("colour",))


def test_info_nce_loss_with_hard_negatives_by_hand():
    text = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    motion = torch.tensor([[1.0, 0.0], [0.6, 0.8]])
    sp = lambda x: math.log1p(math.exp(-x))  # noqa: E731
    t2m = (sp(2 - 1.2) + sp(1.6 - 0)) / 2
    # Motion 0 gets one hard negative at cosine 0.6 (logit 1.2), motion 1 none (masked).
    hard = torch.tensor([[[0.6, 0.8], [1.0, 0.0]], [[1.0, 0.0], [0.0, 1.0]]])
    mask = torch.tensor([[True, False], [False, False]])
    m2t = (-math.log(math.exp(2) / (math.exp(2) + math.exp(0) + math.exp(1.2))) + sp(1.6 - 1.2)) / 2
    assert float(info_nce_loss(text, motion, 2.0, None, hard, mask)) == pytest.approx(
        (t2m + m2t) / 2, abs=1e-6
    )
    # Every hard negative masked: the plain loss; a hard negative equal to the motion costs more.
    plain = float(info_nce_loss(text, motion, 2.0))
    assert float(info_nce_loss(text, motion, 2.0, None, hard, torch.zeros(2, 2, dtype=torch.bool))) == (
        pytest.approx(plain, abs=1e-6)
    )
    assert (
        float(info_nce_loss(text, motion, 2.0, None, motion[:, None], torch.ones(2, 1, dtype=torch.bool)))
        > plain
    )


class FakeCache:
    """Caption -> a sentence embedding whose first value is the caption's length."""

    def lookup(self, captions):
        sentence = torch.tensor([[float(len(c)), 1.0, 0.0] for c in captions])
        return TextEmbedding(
            sentence, torch.zeros(len(captions), 1, 1), torch.ones(len(captions), 1, dtype=bool), 0
        )


def test_collator_pads_each_captions_counterfactuals():
    batch = [
        {"caption": "a man jumps twice", "motion": torch.zeros(8, 4), "length": 8, "name": "a"},
        {"caption": "a man waves", "motion": torch.zeros(4, 4), "length": 4, "name": "b"},
        {"caption": "he runs fast", "motion": torch.zeros(4, 4), "length": 4, "name": "c"},
    ]
    out = CaptionedMotionCollator(FakeCache(), ["count", "speed"])(batch)
    assert out["counterfactual"].shape == (3, 3, 3) and out["sentence"].shape == (3, 3)
    assert out["counterfactual_mask"].tolist() == [[True] * 3, [False] * 3, [True, False, False]]
    # Row 0 holds "a man jumps once", "... three times", "... four times"; row 2 "he runs slow".
    assert out["counterfactual"][0, :, 0].tolist() == [16.0, 23.0, 22.0]
    assert out["counterfactual"][2, 0, 0] == len("he runs slow") and not out["counterfactual"][1].any()
    assert "counterfactual" not in CaptionedMotionCollator(FakeCache())(batch)


class CountingJudge:
    """Embeds a caption by the count it names and a motion by the count in its first feature; or
    neither (reads=False): then every caption ties."""

    WORDS = {"once": 1, "twice": 2, "three times": 3, "four times": 4}

    def __init__(self, reads: bool):
        self.reads = reads

    def embed_texts(self, captions):
        counts = [next((n for w, n in self.WORDS.items() if w in c), 0) for c in captions]
        return torch.stack([self._onehot(n) for n in counts])

    def embed_motions(self, features, lengths):
        return torch.stack([self._onehot(int(round(float(f[0, 0])))) for f in torch.as_tensor(features)])

    def _onehot(self, n):
        z = torch.full((6,), 0.1)
        z[n if self.reads else 0] = 1.0
        return z


def test_counterfactual_ranking_tells_a_judge_that_counts_from_one_that_does_not():
    items = []
    for n, word in [(1, "once"), (2, "twice"), (3, "three times")]:
        features = np.zeros((12, 5), dtype=np.float32)
        features[:, 0] = n
        captions = [SimpleNamespace(text=f"a man jumps {word}"), SimpleNamespace(text="a man jumps")]
        items.append(SimpleNamespace(features=features, length=12, captions=captions))
    # A motion whose count disagrees with its caption: a counting judge ranks a variant first.
    wrong = np.zeros((12, 5), dtype=np.float32)
    wrong[:, 0] = 4
    items.append(
        SimpleNamespace(features=wrong, length=12, captions=[SimpleNamespace(text="he jumps twice")])
    )
    reads = counterfactual_ranking(CountingJudge(True), items)
    assert reads == {"count": {"captions": 4, "first": 0.75, "chance": 0.25}}  # no speed caption: no row
    assert counterfactual_ranking(CountingJudge(False), items)["count"]["first"] == 0.0  # ties never win

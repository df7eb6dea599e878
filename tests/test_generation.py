"""Generation and editing: decoding passes, kept codes, seeds, long sequences, the CLI and its errors."""

import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from mmm.cli import main
from mmm.export.bvh import read_bvh
from mmm.generation.model import TextToMotion
from mmm.generation.prompts import split_paragraph
from mmm.generation.sampler import (
    SamplingConfig,
    draw_codes,
    filter_logits,
    frames_to_codes,
    iteration_counts,
    sample_tokens,
)
from mmm.motion.skeleton import T2M_SKELETON
from mmm.optim import OptimConfig
from mmm.text import TextEmbedding
from mmm.tokenizer.configs import TokenizerLossConfig
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.network import TokenizerConfig
from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig

K = 32


class FakeText(torch.nn.Module):
    """Deterministic embeddings from the characters of the text (no model to load)."""

    name, identity, sentence_dim, word_dim, max_words = "fake", "fake-0", 6, 5, 8

    def encode(self, texts):
        words = torch.zeros(len(texts), 4, 5)
        for i, t in enumerate(texts):
            g = torch.Generator().manual_seed(sum(map(ord, t)))
            words[i] = torch.randn(4, 5, generator=g)
        return TextEmbedding(
            words.mean(1).repeat(1, 2)[:, :6], words, torch.ones(len(texts), 4, dtype=torch.bool), 0
        )


class CountingTransformer(torch.nn.Module):
    """Wraps a transformer and records the batch of every forward pass."""

    def __init__(self, inner):
        super().__init__()
        self.inner, self.calls = inner, []
        self.num_codes, self.cfg = inner.num_codes, inner.cfg
        self.mask_id, self.end_id, self.pad_id = inner.mask_id, inner.end_id, inner.pad_id
        self.part_aware = inner.part_aware

    def forward(self, tokens, *args):
        self.calls.append(tokens.clone())
        return self.inner(tokens, *args)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    tok = TokenizerModule(
        263, TokenizerConfig(width=16, num_codes=K, code_dim=8), OptimConfig(), TokenizerLossConfig()
    )
    tok.train()
    tok.tokenizer(torch.randn(8, 64, 263))
    transformer = MaskedMotionTransformer(
        tok.tokenizer.codebook.detach(),
        TransformerConfig(embed_dim=32, num_heads=4, num_layers=2, dropout=0.0),
        6,
        5,
    )
    return TextToMotion(tok.eval(), transformer.eval(), FakeText(), {"reference": "test"})


def test_schedules_iterations_and_filters():
    cfg = SamplingConfig()
    lengths = torch.tensor([49, 30, 10, 1])
    assert iteration_counts(lengths, lengths, cfg, 50).tolist() == [10, 6, 2, 1]  # ceil(10 L / 50)
    assert iteration_counts(lengths, torch.tensor([5, 0, 3, 1]), cfg, 50).tolist() == [
        10,
        0,
        2,
        1,
    ]  # nothing free: no pass
    assert (
        iteration_counts(lengths, lengths, SamplingConfig(dynamic_iterations=False), 50).tolist() == [10] * 4
    )
    assert frames_to_codes(torch.tensor([40, 41, 196, 195])).tolist() == [10, 11, 49, 49]
    logits = torch.log(torch.tensor([[0.5, 0.3, 0.15, 0.05]]))
    assert torch.isinf(filter_logits(logits, 0.5, None)).tolist() == [[False, False, True, True]]
    assert torch.isinf(filter_logits(logits, None, 0.7)).tolist() == [
        [False, False, True, True]
    ]  # 0.5 + 0.3 >= 0.7
    assert torch.isinf(filter_logits(logits, None, 0.4)).tolist() == [
        [False, True, True, True]
    ]  # always the top code
    with pytest.raises(ValueError, match="schedule must be one of"):
        SamplingConfig(schedule="sqrt")


def test_forward_passes_follow_each_samples_own_count(model):
    counter = CountingTransformer(model.transformer)
    frames = [196, 120, 40, 81]
    codes = frames_to_codes(torch.tensor(frames))
    text = model.encode_text(["a", "b", "c", "d"])
    result = sample_tokens(counter, text, codes, SamplingConfig(), generator=torch.Generator().manual_seed(0))
    expected = [math.ceil(10 * int(c) / 50) for c in codes]
    assert result.iterations.tolist() == expected == [10, 6, 2, 5]
    assert result.forward_passes == len(counter.calls) == max(expected)
    # Pass t holds exactly the samples that still have iterations left; finished ones are never re-predicted.
    assert [len(call) for call in counter.calls] == [
        sum(e > t for e in expected) for t in range(max(expected))
    ]
    assert (result.tokens[torch.arange(4), codes] == model.transformer.end_id).all()
    for i, c in enumerate(codes.tolist()):
        assert bool((result.tokens[i, :c] < K).all())  # every position decoded to a code
    # Lengths that are not multiples of 4 work and are cut back to their frames.
    out = model.generate(["a", "b"], frames=[81, 43], seed=0)
    assert [f.shape for f in out.features] == [(81, 263), (43, 263)] and out.joints[0].shape == (81, 22, 3)


def test_codes_are_drawn_with_their_probabilities():
    probs = torch.tensor([[0.5, 0.0, 0.3, 0.2], [0.0, 0.0, 0.0, 1.0]]).repeat(20000, 1)
    every = torch.arange(len(probs))
    codes = draw_codes(probs, every, len(probs), torch.Generator().manual_seed(0))
    first, second = codes[0::2], codes[1::2]
    freq = torch.bincount(first, minlength=4).float() / len(first)
    # binomial standard error at 20,000 draws: <= 0.0036
    assert torch.allclose(freq, torch.tensor([0.5, 0.0, 0.3, 0.2]), atol=0.015)
    assert int((first == 1).sum()) == 0 and bool((second == 3).all())  # probability 0 is never drawn
    # By hand: position 2 of 3 draws the largest p / -log(u) of the third row of the seed's noise.
    u = torch.rand(3, 4, generator=torch.Generator().manual_seed(5))[2].tolist()
    expected = max(range(4), key=lambda k: [0.5, 0.0, 0.3, 0.2][k] / -math.log(u[k]))
    assert int(draw_codes(probs[:1], torch.tensor([2]), 3, torch.Generator().manual_seed(5))) == expected
    # A position's draw does not depend on which other positions draw.
    alone = draw_codes(probs[:1], torch.tensor([2]), 3, torch.Generator().manual_seed(9))
    assert torch.equal(draw_codes(probs[:3], torch.arange(3), 3, torch.Generator().manual_seed(9))[2:], alone)
    # Coupled across precisions: probabilities 0.1% off (what int8 or bf16 logits do) draw the same code
    # for the same seed almost everywhere, even where the distribution is nearly flat.
    flat = torch.randn(2000, 512, generator=torch.Generator().manual_seed(2)).mul(0.1).softmax(-1)
    noisy = flat * (1 + 1e-3 * torch.randn(flat.shape, generator=torch.Generator().manual_seed(3)))
    codes = [draw_codes(p, torch.arange(2000), 2000, torch.Generator().manual_seed(4)) for p in (flat, noisy)]
    assert float((codes[0] == codes[1]).float().mean()) > 0.98


def test_a_seed_gives_identical_output(model):
    a = model.generate(["walk", "jump"], frames=[80, 120], seed=7)
    b = model.generate(["walk", "jump"], frames=[80, 120], seed=7)
    c = model.generate(["walk", "jump"], frames=[80, 120], seed=8)
    assert all(np.array_equal(x, y) for x, y in zip(a.codes, b.codes))
    assert all(np.array_equal(x, y) for x, y in zip(a.features, b.features))
    assert not all(np.array_equal(x, y) for x, y in zip(a.codes, c.codes))
    guided = model.generate(
        ["walk"],
        frames=[80],
        sampling=SamplingConfig(guidance_scale=2.0, top_k=0.5, top_p=0.9, temperature=0.7),
        seed=7,
    )
    assert (
        guided.forward_passes == 4 and np.isfinite(guided.features[0]).all()
    )  # 20 codes; CFG doubles the batch, not the passes


@pytest.mark.slow
@pytest.mark.parametrize(
    "keep, text, frames, place",
    [
        ([(0, 40), (120, 160)], "a person jumps", None, 0),  # in-betweening
        ([(40, 120)], "a person waves", None, 0),  # outpainting both sides
        ([(0, 160)], None, 196, 32),  # outpainting: the whole source placed in a longer motion, no text
        ([(0, 80)], "then sits", 196, 0),  # completion with text
        ([(0, 80)], None, None, 0),  # completion without text
    ],
)
def test_kept_codes_never_change(model, keep, text, frames, place):
    source = model.generate(["source"], frames=[160], seed=1).features[0]
    source_codes = model.encode_motion(source)
    for seed in range(3):
        out = model.edit(source, keep, text, frames=frames, place=place, seed=seed, num_samples=2)
        kept = out.kept_codes
        offset = place // 4
        idx = np.flatnonzero(kept)
        assert len(idx) > 0 and not kept.all()
        for codes in out.codes:
            assert np.array_equal(codes[idx], source_codes[idx - offset])
        assert out.features[0].shape[0] == (frames or 160)


def test_an_edit_is_as_long_as_its_source_by_default(model):
    source = model.generate(["source"], frames=[162], seed=1).features[0]
    assert source.shape[0] == 162  # not a whole number of codes (4 frames each)
    out = model.edit(source, [(0, 40), (120, 162)], "a person jumps", seed=0)
    assert out.features[0].shape[0] == 162 and out.joints[0].shape[0] == 162
    # 41 codes out; the source's encoding has 40 (its last 2 frames fill no code), so the last is drawn.
    assert out.kept_codes.astype(int).tolist() == [1] * 10 + [0] * 20 + [1] * 10 + [0]
    with pytest.raises(ValueError, match="at least 4"):
        model.edit(source[:3], [(0, 3)], frames=80)


def test_transition_codes_up_to_what_one_sequence_holds(model):
    # 6 context codes of each side and the transition in one sequence of at most 196 / 4 = 49 codes
    out = model.generate_long(["walk", "jump"], frames=[40, 40], seed=0, transition_codes=37)
    assert out.features[0].shape[0] == 40 + 37 * 4 + 40
    for bad in (38, 100, -1):
        with pytest.raises(ValueError, match=rf"\(--transition-codes\) {bad} is outside 0\.\.37"):
            model.generate_long(["walk", "jump"], frames=[40, 40], seed=0, transition_codes=bad)


def test_keep_mask_and_edit_errors(model):
    assert model.keep_mask(10, [(0, 5), (33, 40)]).astype(int).tolist() == [1, 1, 0, 0, 0, 0, 0, 0, 1, 1]
    source = model.generate(["s"], frames=[80], seed=0).features[0]
    with pytest.raises(ValueError, match="nothing to generate"):
        model.edit(source, [(0, 80)])
    with pytest.raises(ValueError, match="goes past the source's 80 frames"):
        model.edit(source, [(0, 100)])
    with pytest.raises(ValueError, match=r"shape \(80, 22\)"):
        model.edit(np.zeros((80, 22)), [(0, 40)])
    with pytest.raises(ValueError, match="outside 40..196"):
        model.generate(["x"], frames=[30])
    with pytest.raises(ValueError, match="text 0 is empty"):
        model.generate([" "], frames=[80])


def test_long_sequence_in_one_decode(model):
    # The passes are counted on the float32 transformer itself (the counter has no layers to convert).
    counter = CountingTransformer(model.transformer)
    model.transformer, inner, precision = counter, model.transformer, model.precision
    model.precision = "fp32"
    try:
        out = model.generate_long(["walk", "jump", "wave"], frames=[80, 120, 40], seed=0, transition_codes=2)
    finally:
        model.transformer, model.precision = inner, precision
    # Segments: one batch of passes (the longest takes ceil(10 * 30 / 50) = 6); transitions: one pass for
    # both.
    assert len(counter.calls) == 6 + 1 and len(counter.calls[-1]) == 2
    assert out.segments == [(0, 80), (88, 208), (216, 256)]
    assert out.features[0].shape == (256, 263)
    seg = model.generate(["walk", "jump", "wave"], frames=[80, 120, 40], seed=0)
    assert np.array_equal(out.codes[0][:20], seg.codes[0]) and np.array_equal(
        out.codes[0][22:52], seg.codes[1]
    )
    # Segments drawn elsewhere (best of N) are used as given: the same ones give the same motion,
    # other ones (a later seed's) give their own codes between the same transitions' places.
    again = model.generate_long(["walk", "jump", "wave"], seed=0, transition_codes=2, segments=seg)
    assert np.array_equal(again.codes[0], out.codes[0]) and np.allclose(again.features[0], out.features[0])
    other = model.generate(["walk", "jump", "wave"], frames=[80, 120, 40], seed=5)
    mixed = model.generate_long(["walk", "jump", "wave"], seed=0, segments=other)
    assert np.array_equal(mixed.codes[0][22:52], other.codes[1]) and mixed.segments == out.segments
    with pytest.raises(ValueError, match="3 texts but 2 segments"):
        model.generate_long(
            ["walk", "jump", "wave"], seed=0, segments=model.generate(["a", "b"], frames=[40, 40], seed=0)
        )


def test_untrained_unconditional_branch_is_warned_about_once(model, caplog):
    source = model.generate(["s"], frames=[80], seed=0).features[0]
    unknown, model.text_dropout = model.text_dropout, 0.1
    try:
        with caplog.at_level("WARNING", logger="mmm.generation.model"):
            model.edit(source, [(0, 40)], None, seed=0)
            model.generate(["s"], frames=[80], sampling=SamplingConfig(guidance_scale=2.0), seed=0)
        assert not caplog.records  # trained with text dropout: nothing to say
        model.text_dropout = 0.0
        with caplog.at_level("WARNING", logger="mmm.generation.model"):
            for _ in range(2):
                model.edit(source, [(0, 40)], None, seed=0)
                model.generate(["s"], frames=[80], sampling=SamplingConfig(guidance_scale=2.0), seed=0)
                model.generate(["s"], frames=[80], seed=0)  # guidance 1 with a text: no warning
                model.generate_long(["a", "b"], frames=[40, 40], seed=0)  # transitions: no warning
        messages = [r.getMessage() for r in caplog.records]
        assert len(messages) == 2, messages
        assert messages[0].startswith("an edit without text") and "corruption.cond_drop=0.1" in messages[0]
        assert messages[1].startswith("classifier-free guidance")
    finally:
        model.text_dropout = unknown
        model._warned.clear()


# (paragraph, prompts): order words are not actions; a fragment of a direction alone repeats the
# verb before it
PARAGRAPHS = [
    (
        "A person walks forward, then turns left. After that they jump twice and finally sit down.",
        ["a person walks forward", "a person turns left", "a person jumps twice", "a person sits down"],
    ),
    ("The man runs; he waves with the right hand", ["the man runs", "the man waves with the right hand"]),
    ("First, walk forward. Next, jump twice.", ["a person walks forward", "a person jumps twice"]),
    (
        "A person walks up the stairs then down the stairs",
        ["a person walks up the stairs", "a person walks down the stairs"],
    ),
    (
        "someone slowly walks forward, then back. Lastly, she waves.",
        ["someone slowly walks forward", "someone walks back", "someone waves"],
    ),
    # "and" before a sequencer, a verb with a comma after it, "before" with a gerund
    (
        "He walks to the left and afterwards he jumps, before sitting down.",
        ["a person walks to the left", "a person jumps", "a person sits down"],
    ),
    # an action noun is its verb, another noun phrase is done; gerunds of every spelling
    (
        "a person squats, followed by a kick with the left leg and then a cartwheel",
        ["a person squats", "a person kicks with the left leg", "a person does a cartwheel"],
    ),
    (
        "The woman waves, followed by jumping. Then raising the arms, before lunging",
        ["the woman waves", "the woman jumps", "the woman raises the arms", "the woman lunges"],
    ),
    # "before" splits only where an action follows
    ("a person walks as before", ["a person walks as before"]),
    ("a man stands before a wall, then he kicks", ["a man stands before a wall", "a man kicks"]),
    # clauses of time put in the order the actions happen; one without an action is dropped
    (
        "The man jumps after walking forward. Before sitting down, he waves.",
        ["the man walks forward", "the man jumps", "the man waves", "the man sits down"],
    ),
    (
        "After he turns left he runs; once done, they sit. When ready, she kicks",
        ["a person turns left", "a person runs", "a person sits", "a person kicks"],
    ),
    (
        "He jumps. Before that, he waves, before that he walks in a circle.",
        ["a person walks in a circle", "a person waves", "a person jumps"],
    ),
    ("a woman squats, before that she waves", ["a woman waves", "a woman squats"]),
    ("someone runs after the ball", ["someone runs after the ball"]),
    ("a person walks to the left and , , then jumps", ["a person walks to the left", "a person jumps"]),
    # lists of verb phrases, one prompt each; a lone "and" and a participle stay with their action
    (
        "Walk forward three steps, turn around and walk back.",
        ["a person walks forward three steps", "a person turns around", "a person walks back"],
    ),
    (
        "A human stumbles, falls, and gets up, then walks forward, swinging the arms",
        ["a human stumbles", "a human falls", "a human gets up", "a human walks forward, swinging the arms"],
    ),
    (
        "they turn and slowly walk away and he sits down",
        ["a person turns and slowly walks away", "a person sits down"],
    ),
    # order words, "starts by", possessives, other subjects, counts
    (
        "First he walks, second he starts by raising his left arm, then his right arm; he ends by a bow",
        [
            "a person walks",
            "a person raises his left arm",
            "a person raises his right arm",
            "a person bows",
        ],
    ),
    (
        "The person lifts the left knee, then the right knee, followed by a hop",
        ["the person lifts the left knee", "the person lifts the right knee", "the person hops"],
    ),
    (
        "person kicks with left leg then two steps forward",
        ["person kicks with left leg", "person does two steps forward"],
    ),
]


def test_paragraph_gerunds_become_third_person_verbs():
    from mmm.generation.prompts import _third_person

    gerunds = (
        "sitting running jogging walking rolling kissing waving dancing circling shuffling raising "
        "pausing making rotating opening entering bowing swinging kneeling lunging tiptoeing crossing"
    )
    verbs = (
        "sits runs jogs walks rolls kisses waves dances circles shuffles raises pauses makes rotates "
        "opens enters bows swings kneels lunges tiptoes crosses"
    )
    assert [_third_person(g) for g in gerunds.split()] == verbs.split()
    assert _third_person("jump,") == "jumps," and _third_person("are") == "is"


def test_paragraph_tells_motion_verbs_in_any_form_from_other_words():
    from mmm.generation.prompts import _motion_verb

    forms = {"walks": "walk", "punches": "punch", "carries": "carry", "goes": "go", "waving": "wave"}
    assert {w: _motion_verb(w) for w in forms} == forms
    assert _motion_verb("Sitting,") == "sit"
    assert [_motion_verb(w) for w in ("arms", "done", "while", "ball", "slowly")] == [None] * 5


def test_paragraph_splitter():
    for paragraph, prompts in PARAGRAPHS:
        assert split_paragraph(paragraph) == prompts
    for nothing in (" . ; ", "then, and finally.", "Then.", "and", "First, then"):
        with pytest.raises(ValueError, match="no action found"):
            split_paragraph(nothing)


def test_trace_plot(model, tmp_path):
    from mmm.generation.trace import plot_trace

    out = model.generate(["walk"], frames=[120], seed=0, trace=True)
    assert len(out.trace.masked) == 6 and out.trace.masked[-1].sum() == 0
    assert [int(m[0].sum()) for m in out.trace.masked] == [
        math.ceil(math.cos(math.pi / 2 * t / 6) * 30 - 1e-6) for t in range(1, 7)
    ]
    png = plot_trace(out.trace, tmp_path / "t.png", title="walk")
    assert png.stat().st_size > 5000


@pytest.mark.slow
def test_cli_generate_writes_complete_sample_folders(trained, tmp_path, capsys):
    dest = tmp_path / "gen"
    code = main(
        [
            "generate",
            "--text",
            "a person walks forward",
            "--length",
            "83",
            "--num-samples",
            "2",
            "--seed",
            "4",
            "--model",
            trained["checkpoint"],
            "--tracking-uri",
            trained["uri"],
            "--out",
            str(dest),
            "--trace",
        ]
    )
    assert code == 0, capsys.readouterr().err
    for k in (0, 1):
        folder = dest / str(k)
        assert {"features.npy", "joints.npy", "motion.gif", "motion.bvh", "meta.json"} <= {
            p.name for p in folder.iterdir()
        }
        features, joints = np.load(folder / "features.npy"), np.load(folder / "joints.npy")
        assert features.shape == (83, 263) and joints.shape == (83, 22, 3)
        meta = json.loads((folder / "meta.json").read_text())
        assert (
            meta["prompt"] == "a person walks forward" and meta["length_frames"] == 83 and meta["seed"] == 4
        )
        assert meta["caption"] == "a person walks forward"  # the GIF's, and `mmm render`'s default
        assert meta["model"]["checkpoint"] == trained["checkpoint"] and meta["model"][
            "text_encoder"
        ].startswith("minilm-")
        assert meta["iterations"] == 5 and set(meta["seconds"]) >= {"text", "sample", "decode", "total"}
        assert meta["length_source"] == "given" and "length_estimator" not in meta
        bvh = read_bvh(folder / "motion.bvh")
        assert bvh.num_frames == 83
        # The BVH encodes the joints with rigid bones: within the deviation it reports.
        error = np.abs(bvh.positions(list(T2M_SKELETON.joint_names)) - joints).max()
        assert error <= meta["bvh_max_deviation_m"] + 1e-3
    assert (dest / "decoding_trace.png").exists()
    # Same seed, same motion.
    again = tmp_path / "again"
    main(
        [
            "generate",
            "--text",
            "a person walks forward",
            "--length",
            "83",
            "--num-samples",
            "2",
            "--seed",
            "4",
            "--model",
            trained["checkpoint"],
            "--tracking-uri",
            trained["uri"],
            "--out",
            str(again),
        ]
    )
    assert np.array_equal(np.load(dest / "1/features.npy"), np.load(again / "1/features.npy"))


@pytest.mark.slow
def test_cli_generate_draws_several_prompts_in_one_call(trained, tmp_path, capsys):
    prompts = ["a person walks forward", "someone jumps twice"]
    common = ["--length", "64", "--num-samples", "2", "--seed", "3", "--model", trained["checkpoint"]]
    common += ["--tracking-uri", trained["uri"]]
    dest = tmp_path / "both"
    argv = ["generate", "--text", prompts[0], "--text", prompts[1], *common, "--out", str(dest)]
    assert main(argv) == 0, capsys.readouterr().err
    assert "4 samples of 2 prompts in" in capsys.readouterr().out
    assert sorted(p.name for p in dest.iterdir()) == ["0", "1", "2", "3"]
    metas = [json.loads((dest / str(k) / "meta.json").read_text()) for k in range(4)]
    assert [(m["prompt"], m["sample"]) for m in metas] == [
        (prompts[0], 0),
        (prompts[0], 1),
        (prompts[1], 0),
        (prompts[1], 1),
    ]
    assert all(np.load(dest / str(k) / "features.npy").shape == (64, 263) for k in range(4))
    # A prompt's samples do not depend on the prompts given with it: alone, the same motions.
    alone = tmp_path / "alone"
    assert main(["generate", "--text", prompts[1], *common, "--out", str(alone)]) == 0
    for k in (0, 1):
        assert np.array_equal(np.load(alone / f"{k}/features.npy"), np.load(dest / f"{k + 2}/features.npy"))
    # An empty prompt among several is refused before anything is drawn.
    bad = tmp_path / "bad"
    assert main(["generate", "--text", prompts[0], "--text", " ", *common, "--out", str(bad)]) != 0
    assert "--text is empty" in capsys.readouterr().err and not bad.exists()
    # A prompt longer than the text encoder reads is drawn from its first tokens, and says so.
    long_prompt = "a person walks forward and then turns around " * 80
    argv = ["generate", "--text", long_prompt, "--text", prompts[0], *common, "--out", str(tmp_path / "cut")]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert err.count("warning: 'a person walks forward and then turns around") == 1
    assert "the rest is left out" in err
    metas = [json.loads((tmp_path / "cut" / str(k) / "meta.json").read_text()) for k in range(4)]
    cut = metas[0]["text_cut"]
    assert cut["tokens"] > cut["read"] > 0 and metas[1]["text_cut"] == cut
    assert "text_cut" not in metas[2] and "text_cut" not in metas[3]
    for k in (0, 1):  # prompts[0] second this time: still its own motions
        assert np.array_equal(
            np.load(tmp_path / "cut" / f"{k + 2}/features.npy"), np.load(dest / f"{k}/features.npy")
        )


@pytest.mark.slow
def test_cli_edit_and_long(trained, tmp_path, capsys):
    from mmm.motion.features import recover_from_ric

    source = tmp_path / "source_joints.npy"  # joints (T, 22, 3) work as a source
    np.save(source, recover_from_ric(np.load(trained["walker"] / "new_joint_vecs/000005.npy")))
    dest = tmp_path / "edit"
    assert (
        main(
            [
                "edit",
                "inbetween",
                "--source",
                str(source),
                "--keep",
                "0:40,80:100",
                "--text",
                "a person jumps",
                "--model",
                trained["checkpoint"],
                "--tracking-uri",
                trained["uri"],
                "--out",
                str(dest),
            ]
        )
        == 0
    ), capsys.readouterr().err
    meta = json.loads((dest / "0/meta.json").read_text())
    assert meta["kind"] == "inbetween" and meta["keep_frames"] == [[0, 40], [80, 100]]
    assert sum(meta["kept_codes"]) == 10 + 5  # codes 0-9 and 20-24
    # the source beside the edit, both as long as the source's features (one frame fewer than its joints)
    assert "with_source.gif" in meta["files"] and meta["caption"] == (
        "inbetween: a person jumps (source frames 0-40, 80-100 kept)"
    )
    with Image.open(dest / "0/with_source.gif") as gif:
        assert (gif.width, gif.n_frames) == (2 * 320, len(np.load(source)) - 1)
    long = tmp_path / "long"
    assert (
        main(
            [
                "generate-long",
                "--paragraph",
                "A person jumps after walking forward, and finally waves.",
                "--lengths",
                "60",
                "--model",
                trained["checkpoint"],
                "--tracking-uri",
                trained["uri"],
                "--out",
                str(long),
            ]
        )
        == 0
    )
    meta = json.loads((long / "0/meta.json").read_text())
    assert meta["prompts"] == ["a person walks forward", "a person jumps", "a person waves"]
    assert np.load(long / "0/features.npy").shape == (60 * 3 + 2 * 8, 263)
    # the split is printed, each prompt with the frames it got
    listed = [line.strip() for line in capsys.readouterr().out.splitlines() if line.startswith("  ")]
    assert listed == [
        f"{i}. {text} (frames {start}-{end})"
        for i, (text, (start, end)) in enumerate(zip(meta["prompts"], meta["segments_frames"]), 1)
    ]
    assert meta["segments_frames"][0][0] == 0 and meta["segments_frames"][-1][1] == 60 * 3 + 2 * 8


@pytest.mark.slow
@pytest.mark.parametrize(
    "argv, message",
    [
        (["generate", "--text", "  ", "--length", "80"], "--text is empty"),
        (["generate", "--text", "walk", "--length", "30"], "--length 30 frames is outside 40..196"),
        (
            ["generate", "--text", "walk", "--length", "80", "--model", "models:/mmm-text2motion@nope"],
            "models:/mmm-text2motion@nope: no such registered model",
        ),
        (
            ["edit", "complete", "--source", "BADSOURCE", "--keep", "0:40"],
            "shape (10, 7), expected features (T, 263) or joints (T, 22, 3)",
        ),
        (
            ["edit", "inbetween", "--source", "BADSOURCE", "--keep", "0:40"],
            "inbetween keeps a start and an end",
        ),
        (["generate-long", "--lengths", "80"], "give the prompts either as --text"),
        (["generate", "--text", "walk", "--candidates", "2", "--trace"], "--trace plots one draw's decoding"),
    ],
)
def test_cli_bad_input_exits_2_and_writes_nothing(trained, tmp_path, capsys, argv, message):
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((10, 7), np.float32))
    argv = [str(bad) if a == "BADSOURCE" else a for a in argv]
    if "--model" not in argv:
        argv += ["--model", trained["checkpoint"]]
    dest = tmp_path / "out"
    assert main(argv + ["--tracking-uri", trained["uri"], "--out", str(dest)]) == 2
    assert message in capsys.readouterr().err
    assert not dest.exists()


@pytest.mark.slow
def test_cli_estimates_the_length_when_none_is_given(trained, tmp_path, capsys):
    from mmm.training.configs import load_length_config
    from mmm.training.length import train_length

    out = trained["out"]
    common = ["--model", trained["checkpoint"], "--tracking-uri", trained["uri"]]
    assert (
        main(
            [
                "generate",
                "--text",
                "a person jumps",
                *common,
                "--length-model",
                str(tmp_path / "none.ckpt"),
                "--out",
                str(tmp_path / "a"),
            ]
        )
        == 2
    )
    assert "pass --length FRAMES, or train one with `make train-length`" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    result = train_length(
        load_length_config(
            [
                f"data.root={trained['walker']}",
                "data.synthesize=null",
                "trainer.max_steps=20",
                "trainer.val_check_interval=10",
                "trainer.enable_progress_bar=false",
                f"output_dir={out}/length",
                f"stage1_output_dir={out}/s1",
                f"token_cache_dir={out}/tokens",
                f"text.cache_dir={out}/text",
                f"logger.tracking_uri={trained['uri']}",
                f"logger.artifact_root={out}/art",
            ]
        )
    )
    assert (
        main(
            [
                "generate",
                "--text",
                "a person jumps",
                *common,
                "--length-model",
                result.best_checkpoint,
                "--out",
                str(tmp_path / "b"),
            ]
        )
        == 0
    )
    meta = json.loads((tmp_path / "b/0/meta.json").read_text())
    assert meta["length_frames"] % 4 == 0 and 40 <= meta["length_frames"] <= 196
    # The sample says its length was a guess, and whose.
    assert meta["length_source"] == "estimated"
    assert meta["length_estimator"] == {
        "reference": result.best_checkpoint,
        "checkpoint": result.best_checkpoint,
    }

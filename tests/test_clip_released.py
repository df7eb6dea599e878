"""CLIP as the released MMM uses it: OpenAI's float16 dtype flow, all 77 word positions, ftfy
clean-up, the real vocabulary, and TorchScript archives read without running them."""

import gzip
import os
import pickle
import re
import struct
import subprocess
import sys
import zipfile
from collections import OrderedDict

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from mmm.text import CaptionEmbeddingCache, build_text_encoder
from mmm.text.clip import CLIPTextEncoder, CLIPTokenizer, find_vocab
from mmm.text.torchscript import UnsafeArchiveError, read_torchscript_tensors

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace/script

TEXTS = ["hello world", "hello world, hi", "world hi hello world hello"]


@pytest.fixture(scope="module")
def tiny_vocab(tmp_path_factory):
    """A valid merges file with a few merges (enough to tokenize TEXTS)."""
    merges = ["h e", "l l", "ll o</w>", "he llo</w>", "w o", "wo r", "wor l", "worl d</w>"]
    path = tmp_path_factory.mktemp("vocab") / "bpe_simple_vocab_16e6.txt.gz"
    path.write_bytes(gzip.compress(("#version: 0.2\n" + "\n".join(merges) + "\n").encode()))
    return path


@pytest.fixture(scope="module")
def state(tiny_vocab):
    """Random text-tower weights, float16-exact like OpenAI's checkpoint, with non-trivial biases
    and LayerNorm gains (CLIP's init leaves them at 0 and 1)."""
    template = CLIPTextEncoder(vocab=tiny_vocab, random_init_seed=0, precision="float32")
    g = torch.Generator().manual_seed(3)
    out = {}
    for key, value in template.model.state_dict().items():
        if key.endswith("bias"):
            value = 0.02 * torch.randn(value.shape, generator=g)
        elif "ln_" in key and key.endswith("weight"):
            value = 1 + 0.1 * torch.randn(value.shape, generator=g)
        out[key] = value.half().float()
    return out


@pytest.fixture(scope="module")
def encoders(state, tiny_vocab):
    """(precision, words) -> encoder, all on the same weights."""
    return {
        (p, w): CLIPTextEncoder(state, vocab=tiny_vocab, precision=p, words=w)
        for p in ("float16", "float32")
        for w in ("eot", "all")
    }


# ------------------------------------------------------------------------------ TorchScript reader


class _Block(nn.Module):
    def __init__(self):
        super().__init__()
        self.attn = nn.MultiheadAttention(8, 2)
        self.ln_1 = nn.LayerNorm(8)
        self.mlp = nn.Sequential(OrderedDict(c_fc=nn.Linear(8, 32), c_proj=nn.Linear(32, 8)))
        self.ln_2 = nn.LayerNorm(8)

    def forward(self, x):  # never called; torch.jit.script needs one
        return x


class _Transformer(nn.Module):
    def __init__(self):
        super().__init__()
        self.resblocks = nn.Sequential(_Block(), _Block())

    def forward(self, x):
        return x


class TinyCLIP(nn.Module):
    """OpenAI's CLIP layout at toy size: float16 Linear/attention weights and projection, float32
    embeddings and LayerNorms, plus sliced (non-contiguous, offset) tensors."""

    def __init__(self):
        super().__init__()
        self.token_embedding = nn.Embedding(16, 8)
        self.positional_embedding = nn.Parameter(torch.randn(5, 8))
        self.transformer = _Transformer()
        self.ln_final = nn.LayerNorm(8)
        for block in self.transformer.resblocks:
            block.attn.half()
            block.mlp.half()
        wide = torch.randn(8, 12).half()
        self.text_projection = nn.Parameter(wide[:, 2:10:2])  # stride (12, 2), offset 2
        self.register_buffer("table", torch.randn(6, 4).t())  # float32, transposed

    def forward(self, ids):
        return self.ln_final(self.token_embedding(ids) + self.positional_embedding[: ids.shape[1]])


@pytest.fixture(scope="module", params=["script", "trace"])
def archive(request, tmp_path_factory):
    torch.manual_seed(0)
    module = TinyCLIP().eval()
    path = tmp_path_factory.mktemp("ts") / f"tiny_{request.param}.pt"
    if request.param == "script":
        torch.jit.script(module).save(str(path))
    else:
        torch.jit.trace(module, torch.zeros(1, 5, dtype=torch.long)).save(str(path))
    return path, module.state_dict()


def test_reader_extracts_every_tensor(archive):
    path, expected = archive
    got = read_torchscript_tensors(path)
    assert sorted(got) == sorted(expected)
    assert (
        "transformer.resblocks.1.attn.in_proj_weight" in got
        and "transformer.resblocks.0.mlp.c_fc.bias" in got
    )
    for key, value in expected.items():
        assert got[key].dtype == value.dtype and got[key].shape == value.shape, key
        assert torch.equal(got[key], value), key
    assert got["transformer.resblocks.0.attn.out_proj.weight"].dtype == torch.float16
    assert got["ln_final.weight"].dtype == torch.float32
    # the sliced tensors are views into their whole storage, as saved
    assert not got["text_projection"].is_contiguous() and got["text_projection"].storage_offset() == 2
    assert not got["table"].is_contiguous()


def _rewrite(src, dst, replace):
    """Copy a zip, replacing members: replace(name, data) -> new data (None: drop the member)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            data = replace(info.filename, zin.read(info.filename))
            if data is not None:
                zout.writestr(info.filename, data)


def _payloads(marker):
    """data.pkl bodies that run code when unpickled: (global they name, bytes)."""

    class System:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    return [
        (f"{os.system.__module__}.system", pickle.dumps(System(), protocol=2)),  # posix.system on Linux
        ("os.system", f"cos\nsystem\n(V touch {marker}\ntR.".encode()),
        ("builtins.exec", f"cbuiltins\nexec\n(Vopen({str(marker)!r}, 'w').close()\ntR.".encode()),
    ]


def test_payload_would_run_with_plain_pickle(tmp_path):
    # control: the payloads used below really do run when unpickled normally
    marker = tmp_path / "ran"
    name, body = _payloads(marker)[2]
    subprocess.run(
        [sys.executable, "-c", "import pickle, sys; pickle.loads(sys.stdin.buffer.read())"],
        input=body,
        check=True,
    )
    assert marker.exists()


@pytest.mark.slow
@pytest.mark.parametrize("which", [0, 1, 2])
def test_reader_refuses_foreign_globals(which, archive, tiny_vocab, tmp_path):
    marker = tmp_path / "ran"
    name, body = _payloads(marker)[which]
    evil = tmp_path / "ViT-B-32.pt"
    _rewrite(archive[0], evil, lambda n, data: body if n.endswith("/data.pkl") else data)
    with pytest.raises(UnsafeArchiveError, match=re.escape(name)) as err:
        read_torchscript_tensors(evil)
    assert str(evil) in str(err.value)
    assert not marker.exists()
    # the encoder refuses it the same way
    with pytest.raises(UnsafeArchiveError, match=re.escape(name)):
        CLIPTextEncoder(evil, vocab=tiny_vocab)
    assert not marker.exists()


def test_code_and_constants_are_never_run(archive, tmp_path):
    marker = tmp_path / "ran"
    python = f"open({str(marker)!r}, 'w').close()\n".encode()
    constants = _payloads(marker)[0][1]

    def poison(name, data):
        if "/code/" in name:
            return python
        return constants if name.endswith("/constants.pkl") else data

    path, expected = archive
    poisoned = tmp_path / "poisoned.pt"
    _rewrite(path, poisoned, poison)
    got = read_torchscript_tensors(poisoned)
    assert sorted(got) == sorted(expected) and all(torch.equal(got[k], v) for k, v in expected.items())
    assert not marker.exists()


@pytest.mark.slow
def test_damaged_archives_name_the_file(archive, tiny_vocab, tmp_path):
    path = archive[0]
    raw = path.read_bytes()
    cases = {}
    cases["not_a_zip.pt"] = b"this is not a checkpoint\n" * 10
    cases["truncated.pt"] = raw[: len(raw) // 2]
    cases["empty.pt"] = b""
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)

    _rewrite(path, tmp_path / "no_data_pkl.pt", lambda n, d: None if n.endswith("/data.pkl") else d)
    _rewrite(
        path, tmp_path / "garbage_pkl.pt", lambda n, d: b"\x80\x02garbage" if n.endswith("/data.pkl") else d
    )
    _rewrite(path, tmp_path / "missing_storage.pt", lambda n, d: None if re.search(r"/data/0$", n) else d)
    _rewrite(path, tmp_path / "short_storage.pt", lambda n, d: d[:2] if re.search(r"/data/\d+$", n) else d)
    # a flipped byte inside a storage: the zip's CRC check catches it
    bad = bytearray(raw)
    with zipfile.ZipFile(path) as z:
        info = next(i for i in z.infolist() if re.search(r"/data/\d+$", i.filename) and i.file_size > 8)
    name_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26 : info.header_offset + 30])
    bad[info.header_offset + 30 + name_len + extra_len + 1] ^= (
        0xFF  # a byte of the data, after the local header
    )
    (tmp_path / "flipped.pt").write_bytes(bytes(bad))

    for name in [
        *cases,
        "no_data_pkl.pt",
        "garbage_pkl.pt",
        "missing_storage.pt",
        "short_storage.pt",
        "flipped.pt",
    ]:
        with pytest.raises(ValueError, match=re.escape(str(tmp_path / name))) as err:
            read_torchscript_tensors(tmp_path / name)
        assert "download it again" in str(err.value), name
    with pytest.raises(FileNotFoundError):
        read_torchscript_tensors(tmp_path / "absent.pt")
    # through the encoder (a cut-off file is no zip any more, so torch.load reports it)
    with pytest.raises(ValueError, match="truncated.pt"):
        build_text_encoder("clip", weights=tmp_path / "truncated.pt", vocab=tiny_vocab)


# ------------------------------------------------------------------------------ real vocabulary

# Token ids from OpenAI's clip/simple_tokenizer.py (with ftfy 6.3) on the open_clip 3.3.0 vocabulary.
SOT, EOT = 49406, 49407
EXPECTED_IDS = {
    "a person walks forward and then turns around.": [
        SOT,
        320,
        2533,
        8192,
        2342,
        537,
        1594,
        3185,
        1630,
        269,
        EOT,
    ],
    "a person says \u201chello\u201d and waves": [SOT, 320, 2533, 1563, 257, 3306, 257, 537, 7882, EOT],
    "the person\u2019s left hand waves": [SOT, 518, 2533, 568, 1823, 2463, 7882, EOT],
    "a man walks to the cafe\u0301 and sits": [SOT, 320, 786, 8192, 531, 518, 15304, 537, 12726, EOT],
    "a person does a \ufb01gure eight with the arm": [
        SOT,
        320,
        2533,
        1897,
        320,
        5274,
        7910,
        593,
        518,
        4793,
        EOT,
    ],
    "\uff41 \uff50\uff45\uff52\uff53\uff4f\uff4e \uff57\uff41\uff4c\uff4b\uff53": [SOT, 320, 2533, 8192, EOT],
    "a person jumps &amp;amp;amp; spins": [SOT, 320, 2533, 18911, 261, 27243, EOT],
    "he says &#8220;stop&#8221; and halts": [SOT, 797, 1563, 257, 1691, 257, 537, 1296, 590, EOT],
    "a person\u00a0walks\u2003forward": [SOT, 320, 2533, 8192, 2342, EOT],
    "it\u00e2\u20ac\u2122s a person running": [SOT, 585, 568, 320, 2533, 2761, EOT],
}
LONG = "a person walks forward then turns left and walks again " * 9  # 92 tokens
LONG_IDS = (
    [SOT]
    + [320, 2533, 8192, 2342, 1594, 3185, 1823, 537, 8192, 1495] * 7
    + [320, 2533, 8192, 2342, 1594, EOT]
)


@pytest.fixture(scope="module")
def real_tokenizer():
    vocab = find_vocab()
    if vocab is None:
        pytest.skip(
            "no installed open_clip/clip package ships bpe_simple_vocab_16e6.txt.gz (make setup installs it)"
        )
    return CLIPTokenizer(vocab)


def test_real_vocabulary_ids_match_openai(real_tokenizer):
    tok = real_tokenizer
    assert (tok.vocab_size, tok.sot_token, tok.eot_token) == (49408, SOT, EOT)
    texts = list(EXPECTED_IDS) + [LONG]
    ids, truncated = tok(texts)
    assert truncated == 1 and tok.count_tokens([LONG]) == [92]
    for row, (text, expected) in enumerate(EXPECTED_IDS.items()):
        assert ids[row, : len(expected)].tolist() == expected, text
        assert ids[row, len(expected) :].abs().sum() == 0, text
    assert len(LONG_IDS) == 77 and ids[-1].tolist() == LONG_IDS  # cut, end-of-text kept last


def test_without_ftfy_the_ids_differ(real_tokenizer, monkeypatch):
    # what ftfy buys: every caption above but the plain one and the whitespace one changes
    monkeypatch.setattr(real_tokenizer, "_fix_text", lambda text: text)
    changed = [t for t, ids in EXPECTED_IDS.items() if [SOT] + real_tokenizer.encode(t) + [EOT] != ids]
    assert len(changed) == 8 and list(EXPECTED_IDS)[0] not in changed


@pytest.mark.slow
def test_ftfy_is_required(tiny_vocab, state, monkeypatch):
    monkeypatch.setitem(sys.modules, "ftfy", None)
    with pytest.raises(ImportError, match="pip install ftfy"):
        CLIPTokenizer(tiny_vocab)
    with pytest.raises(ImportError, match="pip install ftfy"):
        CLIPTextEncoder(state, vocab=tiny_vocab)


# ------------------------------------------------------------------------------ float16 dtype flow


@pytest.mark.slow
def test_float16_weights_follow_openai_convert_weights(encoders):
    dtypes = {k: v.dtype for k, v in encoders["float16", "eot"].model.state_dict().items()}
    half = {k for k, d in dtypes.items() if d == torch.float16}
    expected_half = {"text_projection"} | {
        k
        for k in dtypes
        if re.search(r"\.(attn\.in_proj_(weight|bias)|attn\.out_proj\.\w+|mlp\.c_(fc|proj)\.\w+)$", k)
    }
    assert half == expected_half and len(half) == 1 + 12 * 8
    assert {dtypes["token_embedding.weight"], dtypes["positional_embedding"], dtypes["ln_final.weight"]} == {
        torch.float32
    }
    assert all(v.dtype == torch.float32 for v in encoders["float32", "eot"].model.state_dict().values())


def _openai_block(block, x):
    """One residual block as OpenAI's model.py runs it, written out with torch's own
    nn.MultiheadAttention (sequence first, additive -inf mask in the input dtype); x: (B, L, W)."""

    def layer_norm(ln, t):  # computed in float32, returned in the input dtype
        return F.layer_norm(t.float(), ln.normalized_shape, ln.weight, ln.bias, ln.eps).to(t.dtype)

    L, W = x.shape[1], x.shape[2]
    mha = nn.MultiheadAttention(W, block.attn.heads).to(x.dtype).eval()
    mha.in_proj_weight.data, mha.in_proj_bias.data = block.attn.in_proj_weight, block.attn.in_proj_bias
    mha.out_proj.weight.data, mha.out_proj.bias.data = block.attn.out_proj.weight, block.attn.out_proj.bias
    mask = torch.full((L, L), float("-inf")).triu(1).to(x.dtype)
    x = x.permute(1, 0, 2)  # (L, B, W), as OpenAI's encode_text
    h = layer_norm(block.ln_1, x)
    x = x + mha(h, h, h, need_weights=False, attn_mask=mask)[0]
    h = F.linear(layer_norm(block.ln_2, x), block.mlp.c_fc.weight, block.mlp.c_fc.bias)
    h = h * torch.sigmoid(1.702 * h)
    return (x + F.linear(h, block.mlp.c_proj.weight, block.mlp.c_proj.bias)).permute(1, 0, 2)


@pytest.mark.slow
def test_one_block_matches_the_written_out_flow(encoders):
    torch.manual_seed(0)
    x32 = torch.randn(2, 9, 512)
    with torch.no_grad():
        for precision, dtype in (("float16", torch.float16), ("float32", torch.float32)):
            block = encoders[precision, "eot"].model.transformer.resblocks[0]
            x = x32.to(dtype)
            ours = block(x)
            assert ours.dtype == dtype
            assert torch.equal(ours, _openai_block(block, x)), precision
        # the same weights run in float32 give a visibly different result
        b16, b32 = (encoders[p, "eot"].model.transformer.resblocks[0] for p in ("float16", "float32"))
        diff = (b16(x32.half()).float() - b32(x32.half().float())).abs().max()
        assert 1e-4 < diff < 5e-2


@pytest.mark.slow
def test_float16_encoding_is_openai_flow_not_float32(encoders):
    e16, e32 = encoders["float16", "all"].encode(TEXTS), encoders["float32", "all"].encode(TEXTS)
    assert e16.sentence.dtype == e16.words.dtype == torch.float32
    # computed in float16 and cast at the end: every value is a float16 number
    assert torch.equal(e16.words, e16.words.half().float()) and torch.equal(
        e16.sentence, e16.sentence.half().float()
    )
    assert not torch.equal(e32.words, e32.words.half().float())
    # close to the float32 computation, but not equal to it
    for a, b in ((e16.words, e32.words), (e16.sentence, e32.sentence)):
        torch.testing.assert_close(a, b, atol=5e-2, rtol=5e-2)
        assert (a - b).abs().max() > 1e-4
    # the whole tower written out: embeddings cast to float16, the blocks, ln_final, projection
    model = encoders["float16", "all"].model
    ids, _ = encoders["float16", "all"].tokenizer(TEXTS)
    with torch.no_grad():
        x = model.token_embedding(ids).half() + model.positional_embedding.half()
        for block in model.transformer.resblocks:
            x = _openai_block(block, x)
        ln = model.ln_final
        words = F.layer_norm(x.float(), ln.normalized_shape, ln.weight, ln.bias, ln.eps).half()
        sentence = words[torch.arange(len(TEXTS)), ids.argmax(-1)] @ model.text_projection
    assert torch.equal(e16.words, words.float()) and torch.equal(e16.sentence, sentence.float())


@pytest.mark.slow
def test_words_all_and_eot(encoders):
    for precision in ("float16", "float32"):
        eot, every = encoders[precision, "eot"].encode(TEXTS), encoders[precision, "all"].encode(TEXTS)
        real = eot.word_mask
        assert real.sum(1).tolist() == [4, 7, 8]
        assert every.word_mask.all() and every.word_mask.shape == (3, 77)
        assert torch.equal(every.words[real], eot.words[real]) and torch.equal(every.sentence, eot.sentence)
        assert eot.words[~real].abs().sum() == 0
        assert every.words[~real].abs().amax(-1).gt(0).all()  # positions after EOT are real features
        assert every.truncated == eot.truncated == 0


@pytest.mark.slow
def test_cache_round_trip_with_all_words(encoders, tmp_path):
    enc = encoders["float16", "all"]
    cache = CaptionEmbeddingCache(tmp_path, enc.identity)
    assert cache.build(enc, TEXTS, batch_size=4, progress=False)["added"] == 3
    got, fresh = cache.lookup(TEXTS[::-1]), enc.encode(TEXTS[::-1])
    assert got.words.shape == (3, 77, 512) and got.word_mask.all()
    # float16 features survive the cache's float16 storage exactly
    assert torch.equal(got.words, fresh.words) and torch.equal(got.sentence, fresh.sentence)


# ------------------------------------------------------------------------------ options and identity


@pytest.mark.slow
def test_identity_tracks_options(encoders, state, tiny_vocab, monkeypatch):
    identities = {key: enc.identity for key, enc in encoders.items()}
    assert len(set(identities.values())) == 4
    enc = encoders["float32", "eot"]
    digest = enc._weights_digest()
    monkeypatch.setattr(enc.tokenizer, "cleanup", "none")
    assert enc._weights_digest() != digest
    built = build_text_encoder("clip", weights=state, vocab=tiny_vocab, precision="float32", words="all")
    assert (built.precision, built.words, built.identity) == ("float32", "all", identities["float32", "all"])
    assert CLIPTextEncoder(state, vocab=tiny_vocab).identity == identities["float16", "eot"]  # the defaults
    with pytest.raises(ValueError, match="precision"):
        CLIPTextEncoder(state, vocab=tiny_vocab, precision="bfloat16")
    with pytest.raises(ValueError, match="words"):
        CLIPTextEncoder(state, vocab=tiny_vocab, words="some")


def test_stage2_text_config_passes_the_options():
    from mmm.text.encoders import TextConfig

    options = TextConfig(encoder="clip", clip_precision="float32", clip_words="all").options()
    assert options["precision"] == "float32" and options["words"] == "all"
    default = TextConfig(encoder="clip").options()
    assert (default["precision"], default["words"]) == ("float16", "eot")

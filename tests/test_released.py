"""The authors' released models: strict import of the documented checkpoint layout, export and
re-import, registration and use through every command, the released forward pass as a variant
(one test per documented difference) and the released decoding loop."""

import gzip
import hashlib
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from mmm.cli import main
from mmm.released.keys import ReleasedKeyError, tokenizer_from_released, transformer_from_released
from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig


# -- the documented layout (../shared/spec/released-checkpoints.md), written out here ------------------
def table(rows: int, dim: int) -> torch.Tensor:
    """The fixed sinusoidal table: sin at even dims, cos at odd, frequencies exp(-ln(10000) 2i / dim)."""
    pos = torch.arange(rows, dtype=torch.float32)[:, None]
    freq = torch.exp(-math.log(10000.0) * torch.arange(0, dim, 2, dtype=torch.float32) / dim)
    out = torch.zeros(rows, dim)
    out[:, 0::2], out[:, 1::2] = torch.sin(pos * freq), torch.cos(pos * freq)
    return out


def vq_layout(D=263, W=512, C=32, K=8192, down=2, depth=3) -> dict[str, tuple]:
    shapes = {}

    def conv(name, o, i, k):
        shapes[f"vqvae.{name}.weight"], shapes[f"vqvae.{name}.bias"] = (o, i, k), (o,)

    def res(name):
        for j in range(depth):
            conv(f"{name}.model.{j}.conv1", W, W, 3)
            conv(f"{name}.model.{j}.conv2", W, W, 1)

    conv("encoder.model.0", W, D, 3)
    for i in range(down):
        conv(f"encoder.model.{2 + i}.0", W, W, 4)
        res(f"encoder.model.{2 + i}.1")
    conv(f"encoder.model.{2 + down}", C, W, 3)
    conv("decoder.model.0", W, C, 3)
    for i in range(down):
        res(f"decoder.model.{2 + i}.0")
        conv(f"decoder.model.{2 + i}.2", W, W, 3)
    conv(f"decoder.model.{2 + down}", W, W, 3)
    conv(f"decoder.model.{4 + down}", D, W, 3)
    shapes["vqvae.quantizer.codebook"] = (K, C)
    return shapes


def trans_layout(C=32, K=8192, E=1024, clip=512, cross=2, base=7, head=9, block=51) -> dict[str, tuple]:
    shapes = {
        "trans_base.learn_tok_emb.weight": (3, C),
        "trans_base.to_emb.weight": (E, C),
        "trans_base.to_emb.bias": (E,),
        "trans_base.cond_emb.weight": (E, clip),
        "trans_base.cond_emb.bias": (E,),
        "trans_base.word_emb.weight": (E, clip),
        "trans_base.word_emb.bias": (E,),
        "trans_base.pos_embedding.weight": (block, E),
        "trans_base.pos_embed.embed": (block, 1, E),
        "trans_head.ln_f.weight": (E,),
        "trans_head.ln_f.bias": (E,),
        "trans_head.head.weight": (K, E),
    }

    def block_of(name, is_cross):
        for ln in ("ln1", "ln2") + (("ln3",) if is_cross else ()):
            shapes[f"{name}.{ln}.weight"] = shapes[f"{name}.{ln}.bias"] = (E,)
        for p in ("key", "query", "value", "proj"):
            shapes[f"{name}.attn.{p}.weight"], shapes[f"{name}.attn.{p}.bias"] = (E, E), (E,)
        shapes[f"{name}.mlp.0.weight"], shapes[f"{name}.mlp.0.bias"] = (4 * E, E), (4 * E,)
        shapes[f"{name}.mlp.2.weight"], shapes[f"{name}.mlp.2.bias"] = (E, 4 * E), (E,)
        if is_cross:
            shapes[f"{name}.attn.mask"] = (1, 1, block, 77)

    for i in range(cross):
        block_of(f"trans_base.cross_att.{i}", True)
    for i in range(base):
        block_of(f"trans_base.blocks.{i}", False)
    for i in range(head):
        block_of(f"trans_head.blocks.{i}", False)
    return shapes


SMALL_VQ = dict(D=263, W=16, C=8, K=32, down=2, depth=3)
SMALL_TRANS = dict(C=8, K=32, E=32, clip=512, cross=2, base=1, head=3)  # 2 + 1 + 3 = 6 layers (n = 3)


def random_state(layout: dict[str, tuple], seed: int, make=torch.randn) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    state = {k: (make(*s, generator=g) * 0.2 if make is torch.randn else make(s)) for k, s in layout.items()}
    for k in state:
        if k.endswith("pos_embed.embed"):
            state[k] = table(layout[k][0], layout[k][2]).unsqueeze(1)
        elif k.endswith("attn.mask"):
            state[k] = torch.tril(torch.ones(layout[k][2], 77)).view(layout[k])
    return state


def released_pair(seed=0):
    net = random_state(vq_layout(**SMALL_VQ), seed)
    trans = random_state(trans_layout(**SMALL_TRANS), seed + 1)
    trans.update({f"trans_base.vqvae.{k}": v.clone() for k, v in net.items()})
    return net, trans


# -- strict mapping --------------------------------------------------------------------------------------
def test_paper_size_layout_maps_every_key_onto_the_released_variant():
    from mmm.tokenizer.module import TokenizerModule
    from mmm.transformer.module import MaskedTransformerModule

    vq, tr = vq_layout(), trans_layout()
    assert len(vq) == 67 and len(tr) == 306  # the counts the spec gives
    empty = lambda shape: torch.empty(shape, device="meta")  # noqa: E731 - names and shapes only, no memory
    net = random_state(vq, 0, empty)
    trans = random_state(tr, 0, empty)
    trans.update({f"trans_base.vqvae.{k}": v for k, v in net.items()})
    state, sizes = tokenizer_from_released(net, "vq")
    mapped, inside, tsizes = transformer_from_released(trans, "trans")
    assert set(inside) == set(net)
    cfg = tsizes.config(num_heads=16)
    assert (cfg.num_layers, cfg.num_cross_layers, cfg.embed_dim, cfg.max_tokens, cfg.variant) == (
        18,
        2,
        1024,
        50,
        "released",
    )
    assert (sizes.width, sizes.num_codes, sizes.code_dim, sizes.down_t, sizes.depth) == (512, 8192, 32, 2, 3)
    with torch.device("meta"):
        tok = TokenizerModule(263, sizes.config(), {}, {})
        ours = MaskedTransformerModule(torch.zeros(8192, 32), cfg, {}, {}, 512, 512)
    expected_tok = {k: tuple(v.shape) for k, v in tok.state_dict().items() if k not in ("mean", "std")}
    assert {k: tuple(v.shape) for k, v in state.items()} == expected_tok
    expected = {k: tuple(v.shape) for k, v in ours.state_dict().items() if k != "transformer.codebook"}
    assert {k: tuple(v.shape) for k, v in mapped.items()} == expected
    assert sum(math.prod(s) for s in tr.values()) > 230e6


@pytest.mark.parametrize("which", ["vq", "trans"])
@pytest.mark.parametrize("problem", ["missing", "extra", "shape"])
def test_missing_extra_or_misshaped_keys_are_refused_by_name(which, problem):
    net, trans = released_pair()
    state = net if which == "vq" else trans
    key = (
        "vqvae.decoder.model.2.0.model.1.conv2.weight"
        if which == "vq"
        else "trans_head.blocks.2.attn.value.bias"
    )
    if problem == "missing":
        del state[key]
    elif problem == "extra":
        key = key.replace("weight", "scale").replace("bias", "gain")
        state[key] = torch.zeros(3)
    else:
        state[key] = torch.zeros(5, *state[key].shape[1:])
    with pytest.raises(ReleasedKeyError, match=key.replace(".", r"\.")):
        if which == "vq":
            tokenizer_from_released(net, "vq.pth")
        else:
            transformer_from_released(trans, "trans.pth")


def test_a_modified_sinusoidal_table_or_another_vq_is_refused(tmp_path):
    from mmm.released.importer import ImportRefused, build_tokenizer, build_transformer

    _, trans = released_pair()
    trans["trans_base.pos_embed.embed"] = trans["trans_base.pos_embed.embed"] + 0.1
    with pytest.raises(ReleasedKeyError, match="sinusoidal"):
        transformer_from_released(trans, "trans.pth")
    net, trans = released_pair()
    other, _ = released_pair(seed=7)
    tokenizer = build_tokenizer(other, "other.pth", np.zeros(263, np.float32), np.ones(263, np.float32))

    class Encoder:
        sentence_dim = word_dim = 512

    with pytest.raises(ImportRefused, match="not the one given with --vq"):
        build_transformer(trans, "trans.pth", tokenizer, {}, Encoder(), {}, 2)


# -- files, registration and every command ---------------------------------------------------------------
@pytest.fixture(scope="module")
def release(tmp_path_factory):
    """Released-format files written the way the release writes them, a CLIP text tower in open_clip
    key names (float16 values, as OpenAI ships it), a CLIP vocabulary and evaluator-style stats."""
    from mmm.text.clip import CLIPTextEncoder

    root = tmp_path_factory.mktemp("release")
    net, trans = released_pair()
    torch.save({"net": net}, root / "vq.pth")
    torch.save({"trans": trans}, root / "trans.pth")
    merges = ["h e", "l l", "ll o</w>", "w a", "wa l", "wal k</w>", "p e", "pe r"]
    vocab = root / "bpe_simple_vocab_16e6.txt.gz"
    vocab.write_bytes(gzip.compress(("#version: 0.2\n" + "\n".join(merges) + "\n").encode()))
    clip = CLIPTextEncoder(vocab=vocab, random_init_seed=0, precision="float32")
    torch.save({k: v.half() for k, v in clip.model.state_dict().items()}, root / "clip.bin")
    (root / "meta").mkdir()
    np.save(root / "meta" / "mean.npy", np.random.default_rng(0).normal(size=263).astype(np.float32) * 0.1)
    np.save(
        root / "meta" / "std.npy", np.random.default_rng(1).uniform(0.5, 1.5, size=263).astype(np.float32)
    )
    return {
        "root": root,
        "net": net,
        "trans": trans,
        "vq": root / "vq.pth",
        "transformer": root / "trans.pth",
        "clip": root / "clip.bin",
        "vocab": vocab,
        "stats": root / "meta",
    }


def import_args(release, tmp, *extra):
    return [
        "import",
        "released",
        "--vq",
        str(release["vq"]),
        "--transformer",
        str(release["transformer"]),
        "--stats",
        str(release["stats"]),
        "--clip",
        str(release["clip"]),
        "--clip-vocab",
        str(release["vocab"]),
        "--heads",
        "2",
        "--out-dir",
        str(tmp / "imported"),
        "--tracking-uri",
        f"sqlite:///{tmp}/mlflow.db",
        *extra,
    ]


@pytest.fixture(scope="module")
def imported(release, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("imported")
    assert main(import_args(release, tmp)) == 0
    return {"tmp": tmp, "uri": f"sqlite:///{tmp}/mlflow.db"}


@pytest.mark.slow
def test_import_registers_both_models_tagged_with_the_source_files(release, imported):
    from mlflow import MlflowClient

    client = MlflowClient(imported["uri"])
    sha = {k: hashlib.sha256(release[k].read_bytes()).hexdigest() for k in ("vq", "transformer", "clip")}
    tok = client.get_model_version_by_alias("mmm-tokenizer", "released")
    t2m = client.get_model_version_by_alias("mmm-text2motion", "released")
    assert tok.tags["mmm.imported"] == t2m.tags["mmm.imported"] == "released"
    assert tok.tags["source.vq.sha256"] == t2m.tags["source.vq.sha256"] == sha["vq"]
    assert (
        t2m.tags["source.transformer.sha256"] == sha["transformer"]
        and t2m.tags["source.clip.sha256"] == sha["clip"]
    )
    # The imported checkpoints: the release's statistics and settings, its weights unchanged.
    ckpt = torch.load(
        next((imported["tmp"] / "imported").glob("released-*/transformer-*.ckpt")), weights_only=True
    )
    hp = ckpt["hyper_parameters"]
    assert (
        hp["model"]["variant"] == "released"
        and hp["model"]["num_cross_layers"] == 2
        and hp["corruption"]["cond_drop"] == 0.0
    )
    assert (hp["text_encoder"]["precision"], hp["text_encoder"]["words"]) == ("float16", "all")
    key = release["trans"]["trans_base.blocks.0.attn.key.weight"]
    assert torch.equal(ckpt["state_dict"]["transformer.layers.0.attn.kv.weight"][:32], key)
    tok_ckpt = torch.load(
        next((imported["tmp"] / "imported").glob("released-*/tokenizer.ckpt")), weights_only=True
    )
    assert torch.equal(tok_ckpt["state_dict"]["std"], torch.from_numpy(np.load(release["stats"] / "std.npy")))
    assert tok_ckpt["hyper_parameters"]["encode"]["candidates"] == 1  # the nearest code, as released
    # Importing the same files again reuses the versions.
    assert main(import_args(release, imported["tmp"])) == 0
    assert len(client.search_model_versions("name='mmm-text2motion'")) == 1


@pytest.mark.slow
def test_imported_models_generate_edit_and_serve(release, imported, tmp_path, capsys):
    import mlflow

    model = ["--model", "models:/mmm-text2motion@released", "--tracking-uri", imported["uri"]]
    out = tmp_path / "gen"
    assert (
        main(
            [
                "generate",
                "--text",
                "a person walks",
                "--length",
                "48",
                "--num-samples",
                "2",
                "--out",
                str(out),
                *model,
            ]
        )
        == 0
    )
    joints = np.load(out / "0" / "joints.npy")
    assert joints.shape == (48, 22, 3) and np.isfinite(joints).all()
    assert (
        main(
            [
                "generate",
                "--text",
                "a person walks",
                "--length",
                "48",
                "--out",
                str(tmp_path / "rel"),
                "--decoding",
                "released",
                *model,
            ]
        )
        == 0
    )
    source = np.load(out / "0" / "features.npy")
    assert (
        main(
            [
                "edit",
                "inbetween",
                "--source",
                str(out / "0" / "features.npy"),
                "--keep",
                "0:16,32:48",
                "--text",
                "hello",
                "--out",
                str(tmp_path / "edit"),
                *model,
            ]
        )
        == 0
    )
    edited = np.load(tmp_path / "edit" / "0" / "features.npy")
    assert edited.shape == source.shape
    assert (
        main(
            [
                "edit",
                "complete",
                "--source",
                str(out / "0" / "features.npy"),
                "--keep",
                "0:24",
                "--out",
                str(tmp_path / "done"),
                *model,
            ]
        )
        == 0
    )
    mlflow.set_tracking_uri(imported["uri"])
    served = mlflow.pyfunc.load_model("models:/mmm-text2motion@released")
    rows = served.predict({"text": ["a person walks"], "length": [40], "seed": [3]})
    assert np.asarray(rows[0]["joints"]).shape == (40, 22, 3)


@pytest.mark.slow
def test_export_then_import_gives_identical_weights(release, tmp_path):
    from mmm.generation.model import TextToMotion
    from mmm.released.importer import export_released, import_released

    first = import_released(
        release["vq"],
        release["stats"],
        release["transformer"],
        release["clip"],
        release["vocab"],
        heads=2,
        out_dir=tmp_path / "a",
        register=False,
    )
    # The CLIP files the checkpoint records lie outside outputs/: they are read only when named.
    model = TextToMotion.from_files(
        first.transformer_checkpoint,
        first.tokenizer_checkpoint,
        text_files={"weights": str(release["clip"]), "vocab": str(release["vocab"])},
    )
    net, trans = export_released(model.tokenizer, model.transformer)
    # What the release's own files hold comes back, but the unused learned pos_embedding (not kept).
    assert set(net["net"]) == set(release["net"]) and all(
        torch.equal(net["net"][k], release["net"][k]) for k in net["net"]
    )
    assert set(trans["trans"]) == set(release["trans"])
    differ = [k for k in trans["trans"] if not torch.equal(trans["trans"][k], release["trans"][k])]
    assert differ == ["trans_base.pos_embedding.weight"]
    torch.save(net, tmp_path / "vq.pth")
    torch.save(trans, tmp_path / "trans.pth")
    second = import_released(
        tmp_path / "vq.pth",
        release["stats"],
        tmp_path / "trans.pth",
        release["clip"],
        release["vocab"],
        heads=2,
        out_dir=tmp_path / "b",
        register=False,
    )
    for a, b in (
        (first.tokenizer_checkpoint, second.tokenizer_checkpoint),
        (first.transformer_checkpoint, second.transformer_checkpoint),
    ):
        sa, sb = (
            torch.load(a, weights_only=True)["state_dict"],
            torch.load(b, weights_only=True)["state_dict"],
        )
        assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


@pytest.mark.slow
def test_cli_export_writes_the_released_layout(imported, tmp_path):
    assert (
        main(
            [
                "export",
                "released",
                "--model",
                "models:/mmm-text2motion@released",
                "--tracking-uri",
                imported["uri"],
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    assert len(torch.load(tmp_path / "vq.pth", weights_only=True)["net"]) == len(vq_layout(**SMALL_VQ))
    assert len(torch.load(tmp_path / "trans.pth", weights_only=True)["trans"]) == len(
        trans_layout(**SMALL_TRANS)
    ) + len(vq_layout(**SMALL_VQ))
    # The files are replaced only with --overwrite (the same model writes the same weights again).
    argv = ["export", "released", "--model", "models:/mmm-text2motion@released"]
    argv += ["--tracking-uri", imported["uri"], "--out", str(tmp_path)]
    written = (tmp_path / "vq.pth").stat().st_mtime_ns
    assert main(argv) == 2 and (tmp_path / "vq.pth").stat().st_mtime_ns == written
    assert main([*argv, "--overwrite"]) == 0
    net = torch.load(tmp_path / "vq.pth", weights_only=True)["net"]
    assert (tmp_path / "vq.pth").stat().st_mtime_ns > written and len(net) == len(vq_layout(**SMALL_VQ))


def _bad_inputs(release, tmp):
    stage1_as_stage2 = tmp / "net-as-trans.pth"
    torch.save({"net": release["net"]}, stage1_as_stage2)
    text = tmp / "notes.txt"
    text.write_text("not a checkpoint")
    truncated = tmp / "truncated.pth"
    truncated.write_bytes(release["vq"].read_bytes()[:2000])
    upper = tmp / "upper.pth"
    torch.save(
        {"net": {"encoder_upper.model.0.weight": torch.zeros(2), "quantizer_lower.codebook": torch.zeros(2)}},
        upper,
    )
    empty = tmp / "empty.pth"
    empty.write_bytes(b"")
    mixed_keys = tmp / "mixed-keys.pth"
    torch.save({1: "x", "b": 2}, mixed_keys)
    int_names = tmp / "int-names.pth"
    torch.save({"net": {1: torch.zeros(2), "a": torch.zeros(2)}}, int_names)
    wrong_stats = tmp / "stats"
    wrong_stats.mkdir()
    np.save(wrong_stats / "mean.npy", np.zeros(251, np.float32))
    np.save(wrong_stats / "std.npy", np.ones(251, np.float32))
    return [
        ({"--vq": str(tmp / "absent.pth")}, "absent.pth"),
        ({"--vq": str(tmp)}, str(tmp)),
        ({"--vq": str(text)}, "notes.txt"),
        ({"--vq": str(truncated)}, "truncated.pth"),
        ({"--vq": str(empty)}, "empty.pth"),
        ({"--vq": str(mixed_keys)}, "mixed-keys.pth"),
        ({"--vq": str(int_names)}, "not parameter names"),
        ({"--transformer": str(stage1_as_stage2)}, "net-as-trans.pth"),
        ({"--vq": str(release["transformer"])}, "trans.pth"),
        ({"--vq": str(upper)}, "upper-body pair cannot be mapped"),
        ({"--stats": str(tmp / "nowhere")}, "nowhere"),
        ({"--stats": str(wrong_stats)}, "mean.npy"),
        ({"--clip": str(text)}, "notes.txt"),
        ({"--alias": "champion"}, "promote"),
    ]


@pytest.mark.slow
def test_bad_files_exit_2_naming_the_file_and_change_nothing(release, tmp_path, capsys):
    from mlflow import MlflowClient

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    for changes, needle in _bad_inputs(release, tmp_path):
        args = import_args(release, tmp_path)
        for flag, value in changes.items():
            if flag in args:
                args[args.index(flag) + 1] = value
            else:
                args += [flag, value]
        capsys.readouterr()
        assert main(args) == 2, changes
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, (changes, err)
        assert not (tmp_path / "imported").exists() or not any((tmp_path / "imported").rglob("*.ckpt")), (
            changes
        )
    assert (
        main(
            [
                "import",
                "released-upperbody",
                "--vq",
                str(release["vq"]),
                "--stats",
                str(release["stats"]),
                "--tracking-uri",
                uri,
            ]
        )
        == 2
    )
    assert "height" in capsys.readouterr().err
    assert (
        main(
            import_args(release, tmp_path)[:4]
            + [
                "--transformer",
                str(release["transformer"]),
                "--stats",
                str(release["stats"]),
                "--tracking-uri",
                uri,
            ]
        )
        == 2
    )
    assert "--clip" in capsys.readouterr().err
    assert MlflowClient(uri).search_registered_models() == []


# -- the released forward pass: one test per documented difference ----------------------------------------
CFG = dict(embed_dim=32, num_heads=4, num_layers=4, num_cross_layers=1, dropout=0.0, max_tokens=10)


def twin_models(cross: int = 1):
    """A default (fixed) and a released-variant transformer holding the same weights; the fixed
    one's head bias zeroed, its null text unused."""
    torch.manual_seed(0)
    codebook = torch.randn(20, 6)
    fixed = MaskedMotionTransformer(
        codebook, TransformerConfig(**{**CFG, "num_cross_layers": cross}), 12, 10
    ).eval()
    released = MaskedMotionTransformer(
        codebook, TransformerConfig(**{**CFG, "num_cross_layers": cross, "variant": "released"}), 12, 10
    ).eval()
    with torch.no_grad():
        for p in fixed.parameters():
            p.add_(0.1 * torch.randn_like(p))
        fixed.head.bias.zero_()
    missing, unexpected = released.load_state_dict(fixed.state_dict(), strict=False)
    assert sorted(unexpected) == ["head.bias", "null_sentence", "null_word"] and missing == []
    return fixed, released


def batch(B=3, M=10, K=20, Lw=7, seed=1):
    g = torch.Generator().manual_seed(seed)
    lengths = torch.tensor([9, 5, 2])[:B]
    tokens = torch.randint(0, K, (B, M), generator=g)
    tokens[torch.rand(B, M, generator=g) < 0.3] = K + 2
    for b, n in enumerate(lengths.tolist()):
        tokens[b, n], tokens[b, n + 1 :] = K, K + 1
    word_mask = torch.arange(Lw)[None] < torch.tensor([7, 4, 2])[:B, None]
    return tokens, torch.randn(B, 12, generator=g), torch.randn(B, Lw, 10, generator=g), word_mask


def with_second_table(fixed, M):
    """The fixed model with the table added again to [sentence, tokens] before the self-attention
    layers: the one positional difference, reproduced from outside."""
    rows = table(M + 1, fixed.cfg.embed_dim)
    return fixed.layers[0].register_forward_pre_hook(lambda module, args: (args[0] + rows, *args[1:]))


@pytest.mark.parametrize("cross", [1, 0])
def test_released_positions_add_the_table_again_after_the_sentence(cross):
    fixed, released = twin_models(cross)
    tokens, sentence, words, _ = batch()
    full = torch.ones(words.shape[:2], dtype=torch.bool)
    if cross == 0:  # without local layers the release adds the table once, after the sentence
        fixed.positions.zero_()
    with torch.no_grad():
        before = fixed(tokens, sentence, words, full)
        hook = with_second_table(fixed, tokens.shape[1])
        after = fixed(tokens, sentence, words, full)
        hook.remove()
        theirs = released(tokens, sentence, words, full)
    assert torch.allclose(after, theirs, atol=1e-5)
    assert not torch.allclose(before, theirs, atol=1e-3)


def test_released_cross_attention_reads_every_word_position():
    fixed, released = twin_models()
    tokens, sentence, words, word_mask = batch()
    full = torch.ones_like(word_mask)
    with torch.no_grad():
        hook = with_second_table(fixed, tokens.shape[1])
        fixed_masked, fixed_full = (
            fixed(tokens, sentence, words, word_mask),
            fixed(tokens, sentence, words, full),
        )
        hook.remove()
        theirs = released(tokens, sentence, words, word_mask)
    assert torch.allclose(theirs, fixed_full, atol=1e-5)  # the mask is ignored ...
    assert not torch.allclose(theirs[1:], fixed_masked[1:], atol=1e-3)  # ... where it would hide words


def test_released_head_has_no_bias():
    fixed, released = twin_models()
    assert released.head.bias is None and fixed.head.bias is not None
    assert "head.bias" not in released.state_dict()


def test_released_text_dropout_is_zero_text_with_the_sentence_hidden():
    _, released = twin_models()
    tokens, sentence, words, word_mask = batch()
    drop = torch.tensor([True, False, True])
    with torch.no_grad():
        a = released(tokens, sentence, words, word_mask, drop)
        b = released(tokens, torch.randn_like(sentence), torch.randn_like(words), word_mask, drop)
        zero_text = released(tokens, torch.zeros_like(sentence), torch.zeros_like(words), word_mask)
    assert torch.equal(a[drop], b[drop])  # nothing of the text reaches a dropped sample
    assert not torch.allclose(
        a[drop], zero_text[drop], atol=1e-4
    )  # the sentence token is hidden, not just zero
    assert not hasattr(released, "null_sentence")


def test_released_variant_equals_the_documented_forward_pass():
    """Steps 1-5 of the spec's forward pass written out with plain tensor algebra."""
    _, model = twin_models(cross=2)
    tokens, sentence, words, _ = batch()
    B, M = tokens.shape
    E, H = model.cfg.embed_dim, model.cfg.num_heads
    K = model.num_codes

    def attend(block_attn, q_in, kv_in, key_visible):
        q = block_attn.q(q_in).view(B, -1, H, E // H).transpose(1, 2)
        k, v = block_attn.kv(kv_in).split(E, dim=-1)
        k, v = (t.reshape(B, -1, H, E // H).transpose(1, 2) for t in (k, v))
        scores = q @ k.transpose(-1, -2) / math.sqrt(E // H)
        scores = scores.masked_fill(~key_visible[:, None, None, :], float("-inf"))
        return block_attn.out((scores.softmax(-1) @ v).transpose(1, 2).reshape(B, -1, E))

    def mlp(block, x):
        return block.mlp[2](F.gelu(block.mlp[0](x)))

    with torch.no_grad():
        vectors = torch.where(
            (tokens < K)[..., None],
            model.codebook[tokens.clamp(max=K - 1)],
            model.special.weight[(tokens - K).clamp(min=0)],
        )
        x = model.token_proj(vectors) + table(M, E)
        w = model.word_proj(words)
        for block in model.cross_layers:
            x = x + attend(
                block.attn, block.ln_x(x), block.ln_words(w), torch.ones(B, w.shape[1], dtype=torch.bool)
            )
            x = x + mlp(block, block.ln2(x))
        x = torch.cat((model.sentence_proj(sentence)[:, None], x), 1) + table(M + 1, E)
        visible = torch.cat((torch.ones(B, 1, dtype=torch.bool), tokens != K + 1), 1)
        for block in model.layers:
            h = block.ln1(x)
            x = x + attend(block.attn, h, h, visible)
            x = x + mlp(block, block.ln2(x))
        expected = model.ln_f(x)[:, 1:] @ model.head.weight.T
        got = model(tokens, sentence, words, torch.zeros(B, words.shape[1], dtype=torch.bool))
    assert torch.allclose(got, expected, atol=1e-5)


# -- the released decoding loop ---------------------------------------------------------------------------
class Recorder(torch.nn.Module):
    """A stand-in transformer with fixed logits; records the tokens of every pass."""

    def __init__(self, K=16, M=50, seed=0):
        super().__init__()
        self.num_codes, self.mask_id, self.end_id, self.pad_id = K, K + 2, K, K + 1
        self.cfg = TransformerConfig(embed_dim=8, num_heads=1, num_layers=1, num_cross_layers=0, max_tokens=M)
        self.logits = torch.randn(64, M, K, generator=torch.Generator().manual_seed(seed)) * 3
        self.calls = []

    def forward(self, tokens, sentence, words, word_mask, drop_text=None, condition=None):
        self.calls.append(tokens.clone())
        return self.logits[: tokens.shape[0], : tokens.shape[1]]


def text_for(B):
    from mmm.text.base import TextEmbedding

    return TextEmbedding(torch.zeros(B, 4), torch.zeros(B, 3, 4), torch.ones(B, 3, dtype=torch.bool), 0)


def released_passes(L: int) -> int:
    """The spec's table: 10 passes for 1-2 codes, 2 for 3-7, 1 for 8-12, S = round(10 L / 49) from 13 on."""
    return 10 if L <= 2 else 2 if L <= 7 else 1 if L <= 12 else round(10 * L / 49)


def test_released_decoding_passes_and_masked_counts():
    from mmm.generation.sampler import SamplingConfig, sample_tokens

    cfg = SamplingConfig(decoding="released")
    for L in range(1, 50):
        model = Recorder()
        sample_tokens(model, text_for(1), torch.tensor([L]), cfg, generator=torch.Generator().manual_seed(0))
        assert len(model.calls) == released_passes(L), L
        S = torch.tensor(float(round(10 * L / 49))) + 1e-8  # float32, as the release computes it
        for s, tokens in enumerate(model.calls):
            t = torch.clip(s / S, max=1)
            expected = max(
                int(torch.floor(torch.cos(t * math.pi / 2) * L)), 1
            )  # 6 of 14 at t = 2/3: float32 rounds cos down
            assert int((tokens == model.mask_id).sum()) == expected, (L, s)
    model = Recorder()  # a batch always runs every step
    sample_tokens(
        model, text_for(3), torch.tensor([3, 20, 49]), cfg, generator=torch.Generator().manual_seed(0)
    )
    assert len(model.calls) == 10
    assert all(
        int((c[0] == model.mask_id).sum()) == 1 for c in model.calls[2:]
    )  # the 3-code sample, finished, re-predicts one


def test_released_decoding_remasks_the_least_confident_of_the_last_draw():
    from mmm.generation.sampler import SamplingConfig, sample_tokens

    model = Recorder()
    L = 30
    out = sample_tokens(
        model,
        text_for(1),
        torch.tensor([L]),
        SamplingConfig(decoding="released", temperature=0),
        generator=None,
    )
    probs = model.logits[0].softmax(-1)
    drawn = model.logits[0].argmax(-1)
    assert torch.equal(out.tokens[0, :L], drawn[:L])  # temperature 0: the most likely code everywhere
    # Step 1 masks the n(1) positions whose code drawn at step 0 was least likely.
    n1 = int(math.floor(math.cos(math.pi / 2 * 1 / round(10 * L / 49)) * L))
    confidence = probs[:L].gather(-1, drawn[:L, None])[:, 0]
    expected = set(confidence.argsort()[:n1].tolist())
    assert set((model.calls[1][0] == model.mask_id).nonzero()[:, 0].tolist()) == expected


def test_released_decoding_is_seeded_and_keeps_given_codes():
    from mmm.generation.sampler import SamplingConfig, sample_tokens

    cfg = SamplingConfig(decoding="released")
    runs = [
        sample_tokens(
            Recorder(), text_for(2), torch.tensor([12, 30]), cfg, generator=torch.Generator().manual_seed(s)
        ).tokens
        for s in (5, 5, 6)
    ]
    assert torch.equal(runs[0], runs[1]) and not torch.equal(runs[0], runs[2])
    keep_mask = torch.zeros(2, 30, dtype=torch.bool)
    keep_mask[:, :6] = True
    keep = torch.full((2, 30), 3)
    out = sample_tokens(
        Recorder(),
        text_for(2),
        torch.tensor([12, 30]),
        cfg,
        keep_tokens=keep,
        keep_mask=keep_mask,
        generator=torch.Generator().manual_seed(0),
    ).tokens
    assert (out[:, :6] == 3).all()


def test_released_decoding_refuses_what_the_release_does_not_do():
    from mmm.generation.sampler import SamplingConfig, sample_tokens

    for bad in ({"top_k": 0.5}, {"top_p": 0.9}, {"guidance_scale": 2.0}, {"schedule": "linear"}):
        with pytest.raises(ValueError, match="released decoding"):
            SamplingConfig(decoding="released", **bad)
    with pytest.raises(ValueError, match="decoding=package"):
        sample_tokens(
            Recorder(),
            text_for(1),
            torch.tensor([5]),
            SamplingConfig(decoding="released"),
            no_text=torch.tensor([True]),
        )


# -- evaluator-style statistics -----------------------------------------------------------------------------
def test_evaluator_style_std_matches_the_released_statistics(reference_dir):
    from mmm.data.normalization import evaluator_style_std

    std = np.load(reference_dir / "humanml3d" / "Std.npy")
    released = np.load(reference_dir / "t2m-evaluator-norm" / "std.npy")
    ours = evaluator_style_std(std, 22)
    ratio = ours / released
    assert np.abs(ratio - 1).max() < 0.011  # within 1.1% everywhere (the release's own data snapshot)
    scaled = np.r_[0:4, 259:263]
    assert np.allclose(std[scaled] / ours[scaled], 25.0) and np.array_equal(
        np.delete(ours, scaled), np.delete(std, scaled).astype(np.float32)
    )


def test_data_stats_evaluator_style_writes_a_stats_folder(walker_dataset, tmp_path, capsys):
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(walker_dataset, root)
    assert main(["data", "stats", str(root), "--evaluator-style", "--write"]) == 0
    out = capsys.readouterr().out
    assert "evaluator-style" in out
    std, ref = np.load(root / "evaluator_style" / "std.npy"), np.load(root / "Std.npy")
    assert np.allclose(std[:4] * 25, ref[:4], rtol=1e-3) and np.allclose(std[-4:] * 25, ref[-4:], rtol=1e-3)
    assert np.allclose(std[4:-4], ref[4:-4], rtol=1e-3)


@pytest.mark.parametrize("statistics", ["evaluator_style", "dataset", "files"])
def test_stage1_normalizes_with_the_configured_statistics(walker_dataset, tmp_path, statistics):
    from mmm.data.configs import DataConfig
    from mmm.data.datamodule import TokenizerDataModule
    from mmm.data.normalization import NormalizationConfig

    files = tmp_path / "meta"
    files.mkdir()
    np.save(files / "mean.npy", np.full(263, 0.5, np.float32))
    np.save(files / "std.npy", np.full(263, 2.0, np.float32))
    dm = TokenizerDataModule(
        DataConfig(root=str(walker_dataset), synthesize=None, window=64),
        0,
        NormalizationConfig(statistics=statistics, dir=str(files) if statistics == "files" else None),
    )
    dm.setup("fit")
    std = np.load(walker_dataset / "Std.npy")
    expected = {
        "evaluator_style": np.r_[std[:4] / 25, std[4:-4], std[-4:] / 25],
        "dataset": std,
        "files": np.full(263, 2.0),
    }[statistics]
    assert np.allclose(dm.std, expected, rtol=1e-6)
    window = dm.datasets["train"][0]
    assert window.shape == (64, 263)


@pytest.mark.slow
def test_imported_models_evaluate(imported, tmp_path, capsys):
    from mmm.data.synthetic.generate import generate_dataset

    data = tmp_path / "synthetic"
    generate_dataset(data, num_clips=30, seed=0)
    assert (
        main(
            [
                "evaluate",
                "text2motion=models:/mmm-text2motion@released",
                "what=[adherence]",
                "adherence_max_items=4",
                f"data.root={data}",
                f"logger.tracking_uri={imported['uri']}",
                f"logger.artifact_root={tmp_path}/art",
                f"output_dir={tmp_path}/eval",
            ]
        )
        == 0
    )
    assert "Prompt adherence" in (tmp_path / "eval" / "evaluation.md").read_text()


# -- the paper's recipe, one switch ---------------------------------------------------------------------
def test_recipe_paper_sets_the_released_recipe_for_every_command():
    from mmm.config import ConfigError
    from mmm.pipeline.configs import load_pipeline_config
    from mmm.training.configs import load_length_config, load_stage1_config, load_stage2_config

    s1 = load_stage1_config(["recipe=paper"])
    assert (
        s1.model.tokenizer.width,
        s1.model.tokenizer.num_codes,
        s1.optim.lr,
        s1.optim.warmup_steps,
        list(s1.optim.milestones),
    ) == (512, 8192, 2e-4, 1000, [200000])
    assert (
        s1.data.batch_size,
        s1.trainer.max_steps,
        s1.normalization.statistics,
        s1.normalization.feat_bias,
        s1.refine.steps,
    ) == (256, 300000, "evaluator_style", 25.0, 0)
    default = load_stage1_config([])  # the package's: the decoder refined, half its windows at clip starts
    refine = default.refine
    assert (refine.steps, refine.path_weight, refine.start_windows) == (2000, 0.1, 0.5)
    # and a root-path loss in its own steps, which the release does not have
    assert (default.loss.path_weight, s1.loss.path_weight) == (0.1, 0.0)
    # and it tokenizes known motions by the code search; the release, and an import, the nearest code
    assert (default.encode.candidates, s1.encode.candidates) == (4, 1)
    s2 = load_stage2_config(["recipe=paper"])
    assert (
        s2.model.transformer.num_layers,
        s2.model.transformer.num_cross_layers,
        s2.model.transformer.variant,
    ) == (18, 2, "fixed")
    assert (
        s2.text.encoder,
        s2.text.clip_precision,
        s2.corruption.cond_drop,
        s2.corruption.mask_schedule,
        s2.corruption.pkeep,
    ) == ("clip", "float16", 0.0, "uniform", 0.5)
    assert (
        s2.data.batch_size,
        s2.optim.lr,
        list(s2.optim.betas),
        s2.optim.weight_decay,
        list(s2.optim.milestones),
        s2.trainer.max_steps,
    ) == (128, 2e-4, [0.5, 0.9], 1e-6, [150000], 300000)
    assert load_length_config(["recipe=paper"]).text.encoder == "clip"
    assert load_pipeline_config(["recipe=paper"]).overrides.stage2 == ["recipe=paper"]
    # The command line still wins, and the part-aware commands take the recipe of the config they extend.
    assert (
        load_stage1_config(
            ["recipe=paper", "trainer=cpu", "data.batch_size=8"], parts=True
        ).trainer.accelerator
        == "cpu"
    )
    assert load_stage1_config(["recipe=paper", "data.batch_size=8"]).data.batch_size == 8
    with pytest.raises(ConfigError, match="recipes: paper"):
        load_stage1_config(["recipe=nope"])


def test_root_and_global_loss_terms():
    from mmm.tokenizer.module import TokenizerModule
    from mmm.tokenizer.network import TokenizerConfig

    torch.manual_seed(0)
    target, recon = torch.randn(2, 16, 263) * 0.3, torch.randn(2, 16, 263) * 0.3
    plain = TokenizerModule(263, TokenizerConfig(width=8, num_codes=16), {}, {})
    weighted = TokenizerModule(263, TokenizerConfig(width=8, num_codes=16), {}, {"root_weight": 10.0})
    a, b = plain.losses(recon, target)["recon"], weighted.losses(recon, target)["recon"]
    root = F.smooth_l1_loss(recon[..., :4], target[..., :4], reduction="sum") / recon.numel()
    assert torch.allclose(b - a, 9 * root, atol=1e-6)  # only the 4 root dims, 10x
    glob = TokenizerModule(263, TokenizerConfig(width=8, num_codes=16), {}, {"global_weight": 2.0})
    logged = {}
    glob.log_dict = lambda metrics, **kwargs: logged.update(metrics)
    glob.log = lambda *args, **kwargs: None
    with torch.no_grad():
        loss = glob.training_step(target, 0)
    parts = logged["train/recon"] + 0.5 * logged["train/position"] + 0.02 * logged["train/commit"]
    assert logged["train/global_position_m"] > 0.01
    assert torch.allclose(loss, parts + 2.0 * logged["train/global_position_m"], atol=1e-6)

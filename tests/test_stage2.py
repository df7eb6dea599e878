"""Stage 2: the masked transformer, its corruption and loss, token caching, DDP, end-to-end training."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from mmm.data.datasets import TokenBatchCollator, TokenTextDataset
from mmm.data.humanml3d import Caption, DataError, MotionItem, read_split
from mmm.data.tokens import TokenCache, token_cache_folder, tokenize_dataset
from mmm.fingerprint import dataset_fingerprint, tensors_fingerprint
from mmm.optim import OptimConfig
from mmm.tokenizer.configs import TokenizerLossConfig
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.network import TokenizerConfig
from mmm.transformer.configs import CorruptionConfig
from mmm.transformer.module import MaskedTransformerModule, corrupt, sequence_mean
from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig
from tests.helpers import run_ddp_worker, stage2_overrides, train_tiny_stage1

K = 16


def tiny_transformer(cross=1, layers=3, dropout=0.0):
    torch.manual_seed(0)
    cfg = TransformerConfig(
        embed_dim=32, num_heads=4, num_layers=layers, num_cross_layers=cross, dropout=dropout, max_tokens=12
    )
    return MaskedMotionTransformer(torch.randn(K, 8), cfg, sentence_dim=6, word_dim=5).eval()


def batch_of(lengths, M=12, words=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    lengths = torch.tensor(lengths)
    tokens = torch.full((len(lengths), M), K + 1)
    for i, n in enumerate(lengths.tolist()):
        tokens[i, :n] = torch.randint(0, K, (n,), generator=g)
        tokens[i, n] = K
    word_mask = torch.zeros(len(lengths), words, dtype=torch.bool)
    word_mask[:, :2] = True
    return {
        "tokens": tokens,
        "lengths": lengths,
        "sentence": torch.randn(len(lengths), 6, generator=g),
        "words": torch.randn(len(lengths), words, 5, generator=g),
        "word_mask": word_mask,
    }


def test_transformer_shapes_and_paper_size():
    m = tiny_transformer()
    b = batch_of([5, 11, 1])
    logits = m(b["tokens"], b["sentence"], b["words"], b["word_mask"])
    assert logits.shape == (3, 12, K) and torch.isfinite(logits).all()
    assert not any(n == "codebook" for n, _ in m.named_parameters())  # the stage-1 codebook stays frozen
    with torch.device("meta"):
        paper = MaskedMotionTransformer(torch.empty(8192, 32), TransformerConfig(), 512, 512)
    count = sum(p.numel() for p in paper.parameters())
    assert 225e6 < count < 240e6  # method.md: about 230M
    with torch.device("meta"):
        tiny = MaskedMotionTransformer(
            torch.empty(512, 32), TransformerConfig(embed_dim=192, num_heads=4, num_layers=6), 384, 384
        )
    assert sum(p.numel() for p in tiny.parameters()) < 5e6


def test_padding_and_masked_words_do_not_leak():
    m = tiny_transformer()
    b = batch_of([5, 3])
    base = m(b["tokens"], b["sentence"], b["words"], b["word_mask"])
    words = b["words"].clone()
    words[:, 2:] = 1e3  # masked word positions
    assert torch.allclose(m(b["tokens"], b["sentence"], words, b["word_mask"]), base, atol=1e-5)
    # A shorter padded sequence gives the same logits at its real positions.
    assert torch.allclose(
        m(b["tokens"][:, :7], b["sentence"], b["words"], b["word_mask"])[:, :6], base[:, :6], atol=1e-5
    )
    # Positional encoding is there: shifting the sequence by one changes the logits.
    shifted = torch.roll(b["tokens"], 1, dims=1)
    assert (m(shifted, b["sentence"], b["words"], b["word_mask"])[0, 1:6] - base[0, :5]).abs().max() > 1e-3


def test_dropped_text_and_zero_cross_layers_are_finite():
    m = tiny_transformer(cross=0)
    b = batch_of([4, 4])
    b["word_mask"][:] = False  # no visible word at all
    out = m(b["tokens"], b["sentence"], b["words"], b["word_mask"], drop_text=torch.tensor([True, True]))
    assert torch.isfinite(out).all()
    m2 = tiny_transformer(cross=2)
    dropped = m2(
        b["tokens"], b["sentence"], b["words"], b["word_mask"] | True, drop_text=torch.tensor([True, False])
    )
    other_text = m2(
        b["tokens"],
        b["sentence"] * 5,
        b["words"] * 5,
        b["word_mask"] | True,
        drop_text=torch.tensor([True, False]),
    )
    assert torch.allclose(dropped[0], other_text[0], atol=1e-6)  # a dropped text is ignored entirely
    assert (dropped[1] - other_text[1]).abs().max() > 1e-5  # a kept one is not


def test_corruption_probabilities_out_of_range_are_refused():
    for value in (1.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match=rf"corruption.cond_drop .* in \[0, 1\) .*got {value}"):
            CorruptionConfig(cond_drop=value)
    for value in (1.5, -0.5):
        with pytest.raises(ValueError, match=rf"corruption.pkeep .* in \[0, 1\], got {value}"):
            CorruptionConfig(pkeep=value)
    assert CorruptionConfig(cond_drop=0.999, pkeep=0.0).cond_drop == 0.999


def test_corruption_follows_the_released_scheme():
    lengths = torch.tensor([49, 10, 1, 4] * 50)
    tokens = batch_of(lengths.tolist(), M=50)["tokens"]
    g = torch.Generator().manual_seed(0)
    c = corrupt(tokens, lengths, K, CorruptionConfig(), g)
    real = torch.arange(50)[None] < lengths[:, None]
    assert torch.equal(c.real, real)
    assert torch.equal(c.inputs[~real], tokens[~real])  # END and PAD untouched
    counts = c.masked.sum(1)
    assert bool((counts >= 1).all()) and bool((counts <= lengths).all())
    assert bool((c.masked & ~real).sum() == 0)
    assert bool((c.inputs[c.masked] == K + 2).all())
    ratio = counts[lengths == 49].float() / 49
    assert 0.49 <= ratio.min() and ratio.max() <= 1.0 and 0.68 < ratio.mean() < 0.82  # U(0.5, 1): mean 0.75
    unmasked_real = real & ~c.masked
    share = c.replaced.sum() / unmasked_real.sum()
    assert 0.4 < share < 0.6  # 1 - pkeep of the tokens left visible
    kept = unmasked_real & ~c.replaced
    assert torch.equal(c.inputs[kept], tokens[kept])
    none = corrupt(tokens, lengths, K, CorruptionConfig(pkeep=1.0), g)
    assert not none.replaced.any()
    cosine = corrupt(tokens, lengths, K, CorruptionConfig(mask_schedule="cosine"), g)
    assert cosine.masked.sum(1)[lengths == 49].float().mean() / 49 < 0.75  # E[cos(pi u / 2)] = 2/pi


def test_sequence_mean_weights_each_sequence_equally():
    values = torch.tensor([[1.0, 1.0, 1.0, 1.0], [3.0, 0.0, 0.0, 0.0]])
    weight = torch.tensor([[1, 1, 1, 1], [1, 0, 0, 0]], dtype=torch.bool)
    assert sequence_mean(values, weight).item() == pytest.approx(2.0)


def test_module_loss_averages_each_sequences_masked_positions():
    module = MaskedTransformerModule(
        torch.randn(K, 8),
        TransformerConfig(embed_dim=32, num_heads=4, num_layers=2, dropout=0.0, max_tokens=12),
        OptimConfig(warmup_steps=0),
        CorruptionConfig(loss_on="masked"),
        6,
        5,
    )
    b = batch_of([5, 9])
    c = corrupt(b["tokens"], b["lengths"], K, module.corruption_cfg, torch.Generator().manual_seed(0))
    logits = module.transformer(c.inputs, b["sentence"], b["words"], b["word_mask"])
    loss = module.loss(logits, b["tokens"], c)
    manual = torch.nn.functional.cross_entropy(
        logits.transpose(1, 2), b["tokens"].clamp(max=K - 1), reduction="none"
    )
    expected = torch.stack([manual[i][c.masked[i]].mean() for i in range(2)]).mean()
    assert loss.item() == pytest.approx(expected.item(), rel=1e-6)


def make_item(name, motion_id, start, length, captions):
    return MotionItem(
        name,
        motion_id,
        np.zeros((length, 263), np.float32),
        [Caption(c, (), 0.0, 0.0) for c in captions],
        start=start,
    )


def test_token_text_dataset_spans_augmentation_and_collator():
    tokens = {"000001": np.arange(30)}
    items = [
        make_item("000001", "000001", 0, 120, ["a", "b"]),
        make_item("000001#40-100", "000001", 40, 60, ["c"]),
    ]
    ds = TokenTextDataset(items, tokens, seed=0)
    assert np.array_equal(
        TokenTextDataset(items, tokens, augment=False)[1]["tokens"].numpy(), np.arange(10, 25)
    )
    lengths = {len(ds[2 * k]["tokens"]) for k in range(60)}
    assert lengths == {29, 30}  # one code dropped at the head or tail in about a third of draws
    assert {ds[2 * k]["caption"] for k in range(60)} == {"a", "b"}
    assert ds[5]["caption"] == ds[5]["caption"]  # a function of the (tagged) index

    class Cache:
        def lookup(self, captions):
            from mmm.text import TextEmbedding

            n = len(captions)
            return TextEmbedding(
                torch.zeros(n, 6), torch.zeros(n, 3, 5), torch.ones(n, 3, dtype=torch.bool), 0
            )

    batch = TokenBatchCollator(Cache(), num_codes=64, max_tokens=50)(
        [
            {"tokens": torch.tensor([1, 2, 3]), "caption": "x", "name": "a"},
            {"tokens": torch.tensor([4]), "caption": "y", "name": "b"},
        ]
    )
    assert batch["tokens"].tolist() == [[1, 2, 3, 64], [4, 64, 65, 65]]
    assert batch["lengths"].tolist() == [3, 1] and batch["words"].shape == (2, 3, 5)


def tiny_tokenizer(feature_dim=263, seed=0):
    torch.manual_seed(seed)
    module = TokenizerModule(
        feature_dim, TokenizerConfig(width=16, num_codes=K, code_dim=8), OptimConfig(), TokenizerLossConfig()
    )
    module.train()
    module.tokenizer(torch.randn(4, 64, feature_dim))  # seed the codebook
    return module.eval()


def test_tokens_are_cached_per_tokenizer_and_data(walker_dataset, tmp_path):
    tok = tiny_tokenizer()
    identity = tensors_fingerprint(tok.state_dict())
    fingerprint = dataset_fingerprint(walker_dataset)
    folder = token_cache_folder(tmp_path, identity, fingerprint, tok.encode_cfg.label)
    cache = tokenize_dataset(tok, walker_dataset, folder, progress=False)
    assert len(cache) == 30 and folder.name == f"{identity}-search4x1-{fingerprint}"
    assert json.loads((folder / "meta.json").read_text())["encoding"] == "search4x1"
    assert token_cache_folder(tmp_path, identity, fingerprint).name == f"{identity}-{fingerprint}"  # nearest
    features = np.load(walker_dataset / "new_joint_vecs/000003.npy")
    usable = features.shape[0] // 4 * 4
    x = torch.from_numpy(((features[:usable] - tok.mean.numpy()) / tok.std.numpy())[None].astype(np.float32))
    assert np.array_equal(cache["000003"], tok.encode(x)[0].numpy())  # the code search, as configured
    assert cache["000003"].shape == (usable // 4,)
    other = tiny_tokenizer(seed=1)
    assert tensors_fingerprint(other.state_dict()) != identity  # another tokenizer: another folder
    again = TokenCache(folder)
    assert np.array_equal(again["000003"], cache["000003"])
    with pytest.raises(KeyError, match="nope: no tokens"):
        cache["nope"]


def test_stage2_can_learn_from_the_nearest_codes_of_a_searching_tokenizer(walker_dataset, tmp_path):
    from dataclasses import replace

    from mmm.data.configs import DataConfig
    from mmm.data.datamodule import TokenTextDataModule
    from mmm.training.configs import load_length_config, load_stage2_config
    from mmm.training.length import stage2_view

    tok = tiny_tokenizer()
    nearest = replace(tok.encode_cfg, candidates=1)
    fingerprint = dataset_fingerprint(walker_dataset)
    data = DataConfig(root=str(walker_dataset), synthesize=None)
    for encoding, name in ((None, f"tok-search4x1-{fingerprint}"), (nearest, f"tok-{fingerprint}")):
        dm = TokenTextDataModule(data, 0, tok, "tok", None, None, str(tmp_path), encoding=encoding)
        assert dm._token_folder().name == name
    folder = token_cache_folder(tmp_path, "tok", fingerprint, nearest.label)
    cache = tokenize_dataset(tok, walker_dataset, folder, progress=False, encoding=nearest)
    assert json.loads((folder / "meta.json").read_text())["encoding"] == "nearest"
    assert tok.encode_cfg.candidates == 4  # the tokenizer's own setting is left as it was
    features = np.load(walker_dataset / "new_joint_vecs/000003.npy")
    usable = features.shape[0] // 4 * 4
    x = torch.from_numpy(((features[:usable] - tok.mean.numpy()) / tok.std.numpy())[None].astype(np.float32))
    assert np.array_equal(cache["000003"], tok.tokenizer.encode(x)[0].numpy())  # the nearest code
    searched = tokenize_dataset(tok, walker_dataset, tmp_path / "searched", progress=False)
    differ = [m for m in searched.meta["ids"] if not np.array_equal(cache[m], searched[m])]
    assert differ and all(len(cache[m]) == len(searched[m]) for m in searched.meta["ids"])  # same counts
    # The demo's stage 2 learns from the nearest codes at 1e-3, a tenth of it for its last quarter
    # (README, Stage 2); the quality recipe and the part-aware model stay as they were measured;
    # anything else is refused at load time.
    settings = {
        name: (cfg.token_encoding, cfg.optim.lr, cfg.optim.final_share)
        for name, cfg in (
            ("demo", load_stage2_config()),
            ("quality", load_stage2_config(["recipe=quality"])),
            ("parts", load_stage2_config(parts=True)),
        )
    }
    assert settings == {
        "demo": ("nearest", 1e-3, 0.25),
        "quality": ("tokenizer", 5e-4, 0.0),
        "parts": ("nearest", 5e-4, 0.0),
    }
    # The length estimator reads token counts, the same under any encoding: always the nearest codes.
    assert stage2_view(load_length_config()).token_encoding == "nearest"
    with pytest.raises(Exception, match="token_encoding='search': must be one of tokenizer, nearest"):
        load_stage2_config(["token_encoding=search"])


def test_the_token_cache_is_one_array_and_caches_of_the_first_format_still_read(walker_dataset, tmp_path):
    tok = tiny_tokenizer()
    folder = tmp_path / "tokens"
    cache = tokenize_dataset(tok, walker_dataset, folder, progress=False)
    meta = json.loads((folder / "meta.json").read_text())
    with np.load(folder / "tokens.npz") as archive:
        assert sorted(archive.files) == ["codes", "offsets"]
        codes, offsets = archive["codes"], archive["offsets"]
    assert meta["format"] == 2 and meta["ids"] == sorted(meta["ids"]) and len(meta["ids"]) == 30
    assert offsets[0] == 0 and offsets[-1] == len(codes) and len(offsets) == 31
    for i, motion_id in enumerate(meta["ids"]):
        assert np.array_equal(cache[motion_id], codes[offsets[i] : offsets[i + 1]])
        assert cache[motion_id].dtype == np.int64
    # A cache written before the format existed: one archive entry per motion, no "format".
    old = tmp_path / "old"
    old.mkdir()
    np.savez(old / "tokens.npz", **{m: cache[m].astype(np.int16) for m in meta["ids"]})
    (old / "meta.json").write_text(json.dumps({"splits": meta["splits"]}))
    assert all(np.array_equal(TokenCache(old)[m], cache[m]) for m in meta["ids"])
    # Offsets that do not match the codes: named, with the fix.
    np.savez(folder / "tokens.npz", codes=codes, offsets=offsets[:-1])
    with pytest.raises(DataError, match=r"tokens\.npz: inconsistent token cache .*delete the folder"):
        len(TokenCache(folder))


def test_stage2_tokenizes_only_the_splits_it_reads(trained):
    (meta_file,) = (trained["out"] / "tokens").glob("*/meta.json")
    cache = TokenCache(meta_file.parent)
    root = trained["walker"]
    train, val, test = (read_split(root, split) for split in ("train", "val", "test"))
    assert cache.meta["splits"] == ["train", "val"] and len(test) > 0
    assert sorted(cache.meta["ids"]) == sorted(train + val)
    assert not any(m in cache for m in test)
    with pytest.raises(KeyError, match=rf"{test[0]}: no tokens in .*covers the ids of train, val"):
        cache[test[0]]


def test_a_stage1_model_for_other_features_is_refused(walker_dataset, tmp_path):
    from mmm.data.configs import DataConfig
    from mmm.data.datamodule import TokenTextDataModule

    dm = TokenTextDataModule(
        DataConfig(root=str(walker_dataset), synthesize=None),
        0,
        tiny_tokenizer(feature_dim=251),
        "x",
        None,
        None,
        str(tmp_path),
    )
    with pytest.raises(DataError, match="reads 251-d features but data 'synthetic' has 263"):
        dm.prepare_data()


@pytest.mark.slow
@pytest.mark.ddp
@pytest.mark.parametrize("variant", ["whole", "parts"])
def test_ddp_ranks_agree(tmp_path, variant):
    extra = ["parts"] if variant == "parts" else []
    r0, r1 = run_ddp_worker("stage2_ddp.py", tmp_path, *extra, out_dir=tmp_path)
    assert not torch.equal(r0["first_batch"], r1["first_batch"])  # different data per rank
    assert torch.equal(r0["weights"], r1["weights"])
    # The moving average needs no communication: the same weights after every step on every rank.
    assert torch.equal(r0["average"], r1["average"]) and not torch.equal(r0["average"], r0["weights"])
    assert r0["step"] == r1["step"] == 15
    assert r0["val_loss"] == r1["val_loss"] and r0["val_acc"] == r1["val_acc"]  # reduced across ranks
    # The adherence figures are measured once, on rank 0, and every rank holds rank 0's value.
    assert (r0["measured"], r1["measured"]) == (1, 0)
    assert r0["adherence"] == r1["adherence"] == 0.25


@pytest.mark.slow
def test_train_stage2_end_to_end_uses_the_newest_stage1_and_records_it(walker_dataset, tmp_path):
    from mmm.training.configs import load_stage2_config
    from mmm.training.stage2 import train_stage2

    first = train_tiny_stage1(walker_dataset, tmp_path)
    newest = train_tiny_stage1(walker_dataset, tmp_path)
    result = train_stage2(load_stage2_config(stage2_overrides(walker_dataset, tmp_path)))
    client = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    run = client.get_run(result.run_id)
    assert run.data.tags["stage1.run_id"] == newest.run_id != first.run_id
    assert run.data.tags["text_encoder"].startswith("minilm-")
    assert len(run.data.tags["data.fingerprint"]) == 16
    assert run.data.params["model.transformer.embed_dim"] == "32"
    assert {"val/loss", "val/acc_masked", "val/acc_unmasked", "train/loss"} <= set(run.data.metrics)
    # The demo's schedule: warm-up over 100 steps, then a tenth of the rate for the last quarter of
    # the run's steps, placed from trainer.max_steps (6 here: the last 2).
    history = sorted(client.get_metric_history(result.run_id, "train/lr"), key=lambda m: m.step)
    rates = [m.value for m in history]
    assert rates == pytest.approx([1e-3 * (s + 1) / 100 * (0.1 if s >= 4 else 1.0) for s in range(6)])
    assert {f.path for f in client.list_artifacts(result.run_id, "checkpoints")} == {
        "checkpoints/best.ckpt",
        "checkpoints/last.ckpt",
    }
    previews = sorted(f.path for f in client.list_artifacts(result.run_id, "previews"))
    assert previews == ["previews/generation_step0000003.gif", "previews/generation_step0000006.gif"]
    ckpt = torch.load(result.last_checkpoint, weights_only=True)
    assert ckpt["hyper_parameters"]["codebook_shape"] == [32, 32]
    assert ckpt["hyper_parameters"]["stage1"]["run_id"] == newest.run_id
    # The explicit reference wins, and resuming with a tokenizer of another codebook is refused.
    from mmm.training.common import read_checkpoint_meta
    from mmm.training.stage2 import check_codebook

    last = Path(result.last_checkpoint)
    with pytest.raises(
        ValueError, match=r"codebook of shape \[32, 32\], but the stage-1 model has \[64, 32\]"
    ):
        check_codebook(last, read_checkpoint_meta(last), [64, 32])


@pytest.mark.slow
def test_stage1_references_resolve_to_the_same_model(walker_dataset, tmp_path):
    from mmm.tokenizer.load import ModelNotFound, load_tokenizer, resolve_tokenizer

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    trained = train_tiny_stage1(walker_dataset, tmp_path)
    client = MlflowClient(uri)
    client.create_registered_model("mmm-tokenizer")
    version = client.create_model_version(
        "mmm-tokenizer", source=f"runs:/{trained.run_id}/checkpoints", run_id=trained.run_id
    )
    client.set_registered_model_alias("mmm-tokenizer", "champion", version.version)
    identities = set()
    for reference in (
        trained.run_id,
        f"runs:/{trained.run_id}",
        "models:/mmm-tokenizer@champion",
        f"models:/mmm-tokenizer/{version.version}",
        trained.best_checkpoint,
        None,
    ):
        module, source = load_tokenizer(reference, uri, f"{tmp_path}/s1")
        identities.add(source.identity)
        assert source.checkpoint.endswith("best.ckpt") and module.quantizer.num_codes == 32
    assert len(identities) == 1
    with pytest.raises(ModelNotFound, match="models:/mmm-tokenizer@nope: no such registered model version"):
        resolve_tokenizer("models:/mmm-tokenizer@nope", uri)
    with pytest.raises(
        ModelNotFound, match="no-such.ckpt: no such checkpoint file, MLflow run id or models:/ URI"
    ):
        resolve_tokenizer("no-such.ckpt", uri)
    with pytest.raises(ModelNotFound, match="run `make train-stage1` first"):
        resolve_tokenizer(None, f"sqlite:///{tmp_path}/empty.db", f"{tmp_path}/none")


@pytest.mark.slow
def test_weight_ema_is_what_validation_and_checkpoints_hold_and_a_resume_continues_it(
    walker_dataset, tmp_path, monkeypatch
):
    """callbacks.weight_ema: after every step e = d e + (1 - d) w (e = w after the
    first); validation sees e, best/last.ckpt store e under a fingerprint of e and the weights as
    trained beside it, and a run resumed halfway (at the end of an epoch: 3 batches of 8 of the
    24 walker items) ends as the uninterrupted one, to the bit."""
    import lightning as L

    import mmm.training.stage2 as stage2
    from mmm.checkpoints import load_checkpoint
    from mmm.generation.model import TextToMotion
    from mmm.training.configs import load_stage2_config

    decay = 0.9
    trained, validated = [], []

    class Probe(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, *args):
            trained.append({k: v.detach().clone() for k, v in pl_module.named_parameters()})

        def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0):
            if batch_idx == 0:
                validated.append({k: v.detach().clone() for k, v in pl_module.named_parameters()})

    fit = stage2.tracked_fit
    monkeypatch.setattr(
        stage2,
        "tracked_fit",
        lambda run, cfg, module, target, callbacks, **kw: fit(
            run, cfg, module, target, [*callbacks, Probe()], **kw
        ),
    )
    train_tiny_stage1(walker_dataset, tmp_path)

    def overrides(steps, out="a", **extra):
        return stage2_overrides(
            walker_dataset,
            tmp_path,
            **{
                "callbacks.weight_ema": decay,
                "trainer.max_steps": steps,
                "output_dir": f"{tmp_path}/{out}",
                "callbacks.preview_captions": 0,
                # the last quarter's drop is placed from each leg's max_steps: none, so the legs
                # train as the uninterrupted run does
                "optim.final_share": 0,
                **extra,
            },
        )

    straight = stage2.train_stage2(load_stage2_config(overrides(6)))
    assert len(trained) == 6 and len(validated) == 2  # validations at steps 3 and 6
    average = dict(trained[0])
    expected = []
    for weights in trained[1:]:
        average = {k: decay * average[k] + (1 - decay) * w for k, w in weights.items()}
        expected.append(average)
    for seen, wanted in ((validated[0], expected[1]), (validated[1], expected[4])):
        for k, v in wanted.items():
            assert torch.allclose(seen[k], v, rtol=0, atol=1e-6), k
    last = load_checkpoint(straight.last_checkpoint, "stage2")  # its fingerprint is of the average
    assert last["weight_ema"] == decay
    params = dict(trained[-1])
    for k, v in expected[-1].items():
        assert torch.allclose(last["state_dict"][k], v, rtol=0, atol=1e-6), k
        assert torch.equal(last["current_model_state"][k], params[k]), k
    assert not torch.equal(last["state_dict"]["transformer.head.weight"], params["transformer.head.weight"])
    # The codebook is the stage-1 model's, to the bit: buffers are not averaged.
    codebook = last["current_model_state"]["transformer.codebook"]
    assert torch.equal(last["state_dict"]["transformer.codebook"], codebook)
    # Generation loads the average.
    model = TextToMotion.load(straight.last_checkpoint, f"sqlite:///{tmp_path}/mlflow.db")
    for k, v in model.transformer.state_dict().items():
        assert torch.equal(v, last["state_dict"][f"transformer.{k}"]), k

    first = stage2.train_stage2(load_stage2_config(overrides(3, "b")))
    with pytest.raises(
        ValueError, match=r"averaged its weights with decay 0.9, but callbacks.weight_ema=0.0"
    ):
        stage2.train_stage2(
            load_stage2_config(overrides(6, "b", **{"callbacks.weight_ema": 0})), resume="last"
        )
    resumed = stage2.train_stage2(load_stage2_config(overrides(6, "b")), resume="last")
    assert resumed.run_id == first.run_id
    a, b = (torch.load(r.last_checkpoint, weights_only=True) for r in (straight, resumed))
    assert b["global_step"] == 6
    for part in ("state_dict", "current_model_state"):
        for k, v in a[part].items():
            assert torch.equal(v, b[part][k]), (part, k)

"""The length estimator: shapes, predictions in range, learning a known length, checkpoints, tracked
training."""

import lightning as L
import pytest
import torch
from mlflow.tracking import MlflowClient

from mmm.generation.length import LengthEstimator, LengthModelConfig, length_metrics, load_length_estimator
from mmm.generation.length_module import LengthEstimatorModule
from mmm.optim import OptimConfig
from tests.helpers import train_tiny_stage1


def small(dropout=0.0, **kw):
    torch.manual_seed(0)
    return LengthEstimator(12, LengthModelConfig(hidden_dim=32, dropout=dropout, **kw)).eval()


def test_mlp_shapes_and_default_size():
    net = small()
    assert net(torch.randn(5, 12)).shape == (5, 49)
    assert small(num_layers=1, max_codes=20)(torch.randn(3, 12)).shape == (3, 20)
    with pytest.raises(ValueError, match=r"\(B, 12\)"):
        net(torch.randn(5, 13))
    default = LengthEstimator(384)  # MiniLM's sentence embedding: 384 -> 256 -> 256 -> 49
    linears = [m for m in default.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(384, 256), (256, 256), (256, 49)]
    with pytest.raises(ValueError):
        LengthModelConfig(dropout=1.0)


def test_predict_returns_counts_in_range():
    net = small()
    x = torch.randn(64, 12) * 5
    for mode in ("mode", "sample", "median"):
        n = net.predict(x, mode=mode, generator=torch.Generator().manual_seed(0))
        assert n.dtype == torch.int64 and n.shape == (64,)
        assert int(n.min()) >= 1 and int(n.max()) <= 49
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    assert torch.equal(net.predict(x, "sample", g()), net.predict(x, "sample", g()))
    assert torch.equal(net.frames(x), net.predict(x) * 4)
    # The extreme classes map to 1 and 49 tokens; min/max_codes bound every mode.
    with torch.no_grad():
        net.head.bias.zero_()
        net.head.weight.zero_()
        net.head.bias[0] = 50.0
    assert bool((net.predict(x) == 1).all()) and bool((net.frames(x) == 4).all())
    assert bool((net.predict(x, min_codes=10) == 10).all())
    with torch.no_grad():
        net.head.bias[0], net.head.bias[48] = 0.0, 50.0
    assert bool((net.predict(x) == 49).all()) and bool((net.predict(x, mode="median") == 49).all())
    assert bool((net.predict(x, "sample", g(), max_codes=30) <= 30).all())
    # A flat distribution: the median is the middle count, samples cover the range.
    with torch.no_grad():
        net.head.bias.zero_()
    assert bool((net.predict(x, mode="median") == 25).all())
    samples = net.predict(x.repeat(20, 1), "sample", g())
    assert int(samples.min()) <= 3 and int(samples.max()) >= 47
    with pytest.raises(ValueError):
        net.predict(x, mode="mean")
    with pytest.raises(ValueError):
        net.predict(x, min_codes=0)


def test_length_metrics():
    m = length_metrics(torch.tensor([10, 12, 13, 20]), torch.tensor([10, 11, 11, 30]))
    assert m["acc"].tolist() == [1, 0, 0, 0]
    assert m["acc_within1"].tolist() == [1, 1, 0, 0]
    assert m["acc_within2"].tolist() == [1, 1, 1, 0]
    assert m["mae_frames"].tolist() == [0, 4, 8, 40]


CLUSTER_CODES = (6, 17, 30, 44)


def cluster_pairs(n, seed):
    """Sentence embeddings around 4 centres, each centre with its own count: the count itself with
    probability 0.6, one more or one less with 0.2 each."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.randn(len(CLUSTER_CODES), 12, generator=torch.Generator().manual_seed(123)) * 1.5
    which = torch.randint(0, len(CLUSTER_CODES), (n,), generator=g)
    x = centres[which] + 0.5 * torch.randn(n, 12, generator=g)
    jitter = torch.tensor([-1, 0, 0, 0, 1])[torch.randint(0, 5, (n,), generator=g)]
    codes = torch.tensor(CLUSTER_CODES)[which] + jitter
    return [{"sentence": x[i], "codes": codes[i]} for i in range(n)]


@pytest.mark.slow
def test_module_learns_a_known_length_and_checkpoint_loads_weights_only(tmp_path):
    L.seed_everything(0)
    module = LengthEstimatorModule(
        12,
        LengthModelConfig(hidden_dim=64, dropout=0.1),
        OptimConfig(lr=2e-3, betas=[0.9, 0.999], weight_decay=0.01, warmup_steps=10),
        text_encoder={"name": "fake", "identity": "fake-0"},
        stage1={"identity": "s1"},
    )
    train = torch.utils.data.DataLoader(cluster_pairs(2048, 0), batch_size=64, shuffle=True)
    val = torch.utils.data.DataLoader(cluster_pairs(512, 1), batch_size=128)
    trainer = L.Trainer(
        accelerator="cpu",
        max_steps=200,
        val_check_interval=200,
        check_val_every_n_epoch=None,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
    )
    trainer.fit(module, train, val)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    # The most likely count is the cluster's: within ±1 of every target once the cluster is right.
    # Measured over seeds 0-4 at 150 and 300 steps: within ±1 0.998-1.0, MAE 1.5-1.9 frames, loss 0.93-0.99.
    assert metrics["val/acc_within1"] >= 0.97
    assert metrics["val/acc_within2"] >= 0.97
    assert metrics["val/mae_frames"] < 3.0
    assert metrics["val/loss"] < 1.1  # 0.95 is the floor: the entropy of (0.2, 0.6, 0.2)
    # Untrained, the same network is far off.
    fresh = LengthEstimator(12, LengthModelConfig(hidden_dim=64)).eval()
    batch = next(iter(val))
    assert float(length_metrics(fresh.predict(batch["sentence"]), batch["codes"])["acc_within1"].mean()) < 0.5

    path = tmp_path / "length.ckpt"
    trainer.save_checkpoint(path)
    ckpt = torch.load(path, weights_only=True)
    hp = ckpt["hyper_parameters"]
    assert (
        hp["model"]["hidden_dim"] == 64
        and hp["sentence_dim"] == 12
        and hp["text_encoder"]["identity"] == "fake-0"
    )
    loaded = load_length_estimator(path)
    assert (
        not loaded.training
        and loaded.text_encoder["identity"] == "fake-0"
        and loaded.stage1 == {"identity": "s1"}
    )
    module.eval()
    assert torch.allclose(
        loaded.logits(batch["sentence"]), module.estimator.logits(batch["sentence"]), atol=1e-6
    )
    assert torch.equal(loaded.predict(batch["sentence"]), module.estimator.predict(batch["sentence"]))
    with pytest.raises(ValueError, match="not a length estimator checkpoint"):
        torch.save({"hyper_parameters": {"model": {}}, "state_dict": {}}, tmp_path / "other.ckpt")
        load_length_estimator(tmp_path / "other.ckpt")


def test_word_pooling_shapes_padding_and_refusals():
    torch.manual_seed(0)
    net = LengthEstimator(
        12, LengthModelConfig(hidden_dim=32, dropout=0.0, pooling="words"), word_dim=8
    ).eval()
    sentence, words = torch.randn(3, 12), torch.randn(3, 5, 8)
    mask = torch.tensor([[True] * 5, [True] * 2 + [False] * 3, [True] + [False] * 4])
    logits = net(sentence, words, mask)
    assert logits.shape == (3, 49)
    # What sits at padded positions never reaches the prediction.
    noisy = words.clone()
    noisy[~mask] = 100.0
    assert torch.allclose(net(sentence, noisy, mask), logits, atol=1e-6)
    assert net.predict(sentence, words=words, word_mask=mask).shape == (3,)
    with pytest.raises(ValueError, match="reads the caption's words"):
        net(sentence)
    with pytest.raises(ValueError, match=r"\(B=3, L, 8\)"):
        net(sentence, torch.randn(3, 5, 9), mask)
    with pytest.raises(ValueError, match="needs the text encoder's word_dim"):
        LengthEstimator(12, LengthModelConfig(pooling="words"))
    with pytest.raises(ValueError, match="pooling must be one of sentence, words"):
        LengthModelConfig(pooling="tokens")
    # A sentence-pooled estimator ignores words given to it (one call site serves both).
    plain = small()
    x = torch.randn(3, 12)
    assert torch.equal(plain(x), plain(x, words, mask))


def test_word_pooling_learns_what_the_sentence_embedding_hides():
    """Two captions with the same sentence embedding, one with a second verb token (the second
    action of "walks forward and jumps"): 10 and 30 tokens. Only the word pool can tell them apart."""
    torch.manual_seed(0)
    n, dw = 256, 8
    second = torch.rand(n) < 0.5
    sentence = torch.ones(n, 12)
    words = torch.zeros(n, 3, dw)
    words[:, 0, 0] = 1.0  # the first verb, in every caption
    words[second, 1, 1] = 1.0  # the second verb
    mask = torch.ones(n, 3, dtype=torch.bool)
    mask[~second, 1:] = False
    codes = torch.where(second, 30, 10)
    accuracy = {}
    for pooling in ("sentence", "words"):
        torch.manual_seed(0)
        net = LengthEstimator(12, LengthModelConfig(hidden_dim=32, dropout=0.0, pooling=pooling), word_dim=dw)
        optimizer = torch.optim.Adam(net.parameters(), lr=1e-2)
        for _ in range(150):
            loss = torch.nn.functional.cross_entropy(net(sentence, words, mask), codes - 1)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        net.eval()
        predicted = net.predict(sentence, words=words, word_mask=mask)
        accuracy[pooling] = float((predicted == codes).float().mean())
    assert accuracy["words"] == 1.0
    assert accuracy["sentence"] <= 0.6  # one count for both: the share of the more frequent one


def test_a_checkpoint_without_pooling_reads_the_sentence_only(tmp_path):
    """Estimators trained before the word pool record neither `pooling` nor `word_dim`."""
    module = LengthEstimatorModule(12, LengthModelConfig(hidden_dim=16))
    hp = dict(module.hparams)
    hp["model"] = {k: v for k, v in hp["model"].items() if k != "pooling"}
    hp.pop("word_dim")
    state = {f"estimator.{k}": v for k, v in module.estimator.state_dict().items()}
    torch.save({"hyper_parameters": hp, "state_dict": state}, tmp_path / "old.ckpt")
    loaded = load_length_estimator(tmp_path / "old.ckpt")
    x = torch.randn(4, 12)
    assert not loaded.reads_words and torch.allclose(loaded(x), module.estimator.eval()(x), atol=1e-6)


def _train_stage1(root, out):
    return train_tiny_stage1(root, out)


@pytest.mark.slow
def test_train_length_end_to_end_is_tracked(walker_dataset, tmp_path):
    from mmm.training.configs import load_length_config
    from mmm.training.length import train_length

    stage1 = _train_stage1(walker_dataset, tmp_path)
    overrides = {
        "data.root": walker_dataset,
        "data.synthesize": "null",
        "data.batch_size": 8,
        "model.hidden_dim": 16,
        "trainer.max_steps": 6,
        "trainer.val_check_interval": 3,
        "trainer.log_every_n_steps": 1,
        "trainer.enable_progress_bar": "false",
        "output_dir": f"{tmp_path}/len",
        "stage1_output_dir": f"{tmp_path}/s1",
        "token_cache_dir": f"{tmp_path}/tokens",
        "text.cache_dir": f"{tmp_path}/text",
        "logger.tracking_uri": f"sqlite:///{tmp_path}/mlflow.db",
        "logger.artifact_root": f"{tmp_path}/art",
    }
    result = train_length(load_length_config([f"{k}={v}" for k, v in overrides.items()]))
    client = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    run = client.get_run(result.run_id)
    assert client.get_experiment(run.info.experiment_id).name == "mmm-length"
    tags = run.data.tags
    assert tags["mmm.stage"] == "length" and tags["stage1.run_id"] == stage1.run_id
    assert tags["text_encoder"].startswith("minilm-") and len(tags["data.fingerprint"]) == 16
    assert (
        tags["length.train_pairs"] == "24" and tags["length.val_pairs"] == "3"
    )  # walker items: one caption each
    assert (
        run.data.params["model.hidden_dim"] == "16" and run.data.params["logger.experiment"] == "mmm-length"
    )
    expected = {
        "train/loss",
        "val/loss",
        "val/acc",
        "val/acc_within1",
        "val/acc_within2",
        "val/mae_frames",
        "baseline/acc_within1",
        "time/fit_s",
    }
    assert expected <= set(run.data.metrics)
    assert len(client.get_metric_history(result.run_id, "train/loss")) == 6  # every step
    assert len(client.get_metric_history(result.run_id, "val/acc_within1")) == 2
    artifacts = {f.path for f in client.list_artifacts(result.run_id)}
    assert "config.yaml" in artifacts
    assert {f.path for f in client.list_artifacts(result.run_id, "checkpoints")} == {
        "checkpoints/best.ckpt",
        "checkpoints/last.ckpt",
    }
    assert 0.0 <= result.metrics["val/acc_within1"] <= 1.0 and result.metrics["val/mae_frames"] >= 0.0
    # The checkpoint loads without code and predicts from the encoder it names.
    ckpt = torch.load(result.best_checkpoint, weights_only=True)
    assert ckpt["hyper_parameters"]["stage1"]["run_id"] == stage1.run_id
    assert ckpt["hyper_parameters"]["text_encoder"]["identity"] == tags["text_encoder"]
    estimator = load_length_estimator(result.best_checkpoint)
    from mmm.text import CaptionEmbeddingCache

    text = CaptionEmbeddingCache(f"{tmp_path}/text", tags["text_encoder"]).lookup(["a person turns"])
    # The default pools the caption's words beside its sentence embedding: both are recorded and needed.
    assert estimator.reads_words and ckpt["hyper_parameters"]["word_dim"] == text.words.shape[-1]
    assert run.data.params["model.pooling"] == "words"
    frames = estimator.frames(text.sentence, words=text.words, word_mask=text.word_mask)
    assert frames.shape == (1,) and 4 <= int(frames) <= 196 and int(frames) % 4 == 0
    with pytest.raises(ValueError, match="reads the caption's words"):
        estimator.frames(text.sentence)

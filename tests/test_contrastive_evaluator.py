"""The contrastive text-motion evaluator: shapes and length masking, the InfoNCE loss by hand,
learning a toy retrieval problem, weights-only checkpoints, the raw-input embedder, and a tracked,
registered end-to-end training run."""

import math
from pathlib import Path
from types import SimpleNamespace

import lightning as L
import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from mmm.evaluation.contrastive import (
    ContrastiveEvaluator,
    EvaluatorEmbedder,
    load_contrastive_evaluator,
    matching_ranks,
    retrieval_metrics,
)
from mmm.evaluation.contrastive_module import ContrastiveEvaluatorModule, false_negative_mask, info_nce_loss
from mmm.text import TextEmbedding
from mmm.training.configs import ContrastiveModelConfig

D, DS = 16, 24  # toy feature and sentence dims


def small_evaluator(**kw) -> ContrastiveEvaluator:
    torch.manual_seed(0)
    cfg = {"embed_dim": 32, "hidden_dim": 32, "text_hidden_dim": 32, "dropout": 0.0, **kw}
    return ContrastiveEvaluator(D, DS, cfg).eval()


@pytest.mark.slow
def test_shapes_and_padding_does_not_change_a_motion_embedding():
    ev = small_evaluator()
    g = torch.Generator().manual_seed(0)
    lengths = torch.tensor([40, 23, 4, 17, 31])
    motion = torch.randn(5, 40, D, generator=g)
    with torch.no_grad():
        emb = ev.embed_motions(motion, lengths)
        assert emb.shape == (5, 32)
        assert torch.allclose(emb.norm(dim=-1), torch.ones(5), atol=1e-5)  # L2-normalized by default
        # Garbage past each length, and a longer padded batch, change nothing.
        garbage = torch.cat((motion, torch.randn(5, 25, D, generator=g)), dim=1)
        for i, n in enumerate(lengths.tolist()):
            garbage[i, n:] = 1e3 * torch.randn(garbage.shape[1] - n, D, generator=g)
        assert torch.allclose(ev.embed_motions(garbage, lengths), emb, atol=1e-5)
        # Each motion alone, unpadded, gives its row of the batch.
        for i, n in enumerate(lengths.tolist()):
            alone = ev.embed_motions(motion[i : i + 1, :n], lengths[i : i + 1])
            assert torch.allclose(alone[0], emb[i], atol=1e-5)
        # But the frames inside the length do count.
        changed = motion.clone()
        changed[1, 5] += 3.0
        assert not torch.allclose(ev.embed_motions(changed, lengths)[1], emb[1], atol=1e-4)
        text = ev.embed_sentences(torch.randn(7, DS, generator=g))
        assert text.shape == (7, 32) and torch.allclose(text.norm(dim=-1), torch.ones(7), atol=1e-5)
        raw = small_evaluator(normalize=False)
        assert not torch.allclose(raw.embed_motions(motion, lengths).norm(dim=-1), torch.ones(5), atol=1e-3)
    with pytest.raises(ValueError, match=r"\(B, T, 16\)"):
        ev.embed_motions(torch.randn(2, 10, D + 1), torch.tensor([10, 10]))
    with pytest.raises(ValueError, match="lengths"):
        ev.embed_motions(
            torch.randn(2, 10, D), torch.tensor([10, 3])
        )  # shorter than the 4 frames it downsamples by
    with pytest.raises(ValueError, match="lengths"):
        ev.embed_motions(torch.randn(2, 10, D), torch.tensor([10, 11]))
    with pytest.raises(ValueError, match=r"\(B, 24\)"):
        ev.embed_sentences(torch.randn(2, DS + 1))
    with pytest.raises(ValueError):
        ContrastiveModelConfig(init_temperature=0.001)  # 1/T above the logit-scale cap


def test_info_nce_loss_on_a_hand_made_2x2_case():
    text = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    motion = torch.tensor([[1.0, 0.0], [0.6, 0.8]])
    # logits = 2 * cos = [[2, 1.2], [0, 1.6]]; rows: text->motion, columns: motion->text.
    sp = lambda x: math.log1p(math.exp(-x))  # noqa: E731  -log(e^a / (e^a + e^b)) = log(1 + e^(b - a))
    t2m = (sp(2 - 1.2) + sp(1.6 - 0)) / 2
    m2t = (sp(2 - 0) + sp(1.6 - 1.2)) / 2
    assert float(info_nce_loss(text, motion, 2.0)) == pytest.approx((t2m + m2t) / 2, abs=1e-6)
    # Inputs are L2-normalized inside: scaling an embedding changes nothing.
    assert float(info_nce_loss(3 * text, 0.5 * motion, torch.tensor(2.0))) == pytest.approx(
        (t2m + m2t) / 2, abs=1e-6
    )
    # Pair (0, 1) left out of the negatives: row 0 and column 1 keep only their positive (loss 0).
    exclude = torch.tensor([[False, True], [False, False]])
    assert float(info_nce_loss(text, motion, 2.0, exclude)) == pytest.approx(
        (sp(1.6) / 2 + sp(2.0) / 2) / 2, abs=1e-6
    )
    # The diagonal is never excluded.
    assert float(info_nce_loss(text, motion, 2.0, torch.eye(2, dtype=torch.bool))) == pytest.approx(
        (t2m + m2t) / 2, abs=1e-6
    )
    # Perfectly matched, well separated pairs at a high scale: loss near zero.
    assert float(info_nce_loss(torch.eye(4), torch.eye(4), 100.0)) < 1e-6
    # Near-identical captions are marked (off the diagonal only); no threshold: no mask.
    s = torch.tensor([[1.0, 0.0], [0.999, 0.04], [0.0, 1.0]])
    assert false_negative_mask(s, 0.95).tolist() == [
        [False, True, False],
        [True, False, False],
        [False, False, False],
    ]
    assert false_negative_mask(s, None) is None


def test_retrieval_ranks_and_r_precision_by_hand():
    text = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    motion = torch.tensor([[0.1, 0.0], [0.8, 0.3], [0.9, 0.0]])
    # Distances text (rows) x motion (columns):
    #   t0: 0.1    0.854  0.9
    #   t1: 0.9    0.361  0.1     own motion second nearest
    #   t2: 1.005  1.063  1.345   own motion third nearest
    t2m, m2t = matching_ranks(text, motion)
    assert t2m.tolist() == [0, 1, 2] and m2t.tolist() == [0, 0, 2]
    scores = retrieval_metrics([text], [motion])
    assert scores["r_precision_top1"] == pytest.approx(1 / 3)
    assert scores["r_precision_top2"] == pytest.approx(2 / 3) and scores["r_precision_top3"] == pytest.approx(
        1.0
    )
    expected = (0.1 + math.hypot(0.2, 0.3) + math.hypot(0.9, 1.0)) / 3
    assert scores["matching_distance"] == pytest.approx(expected, abs=1e-6)
    two = retrieval_metrics([text, text], [motion, text])  # a perfect second batch: hits summed over both
    assert two["r_precision_top1"] == pytest.approx(4 / 6) and two["r_precision_top2"] == pytest.approx(5 / 6)


# ----------------------------------------------------------------------------- a toy problem

CLASSES, T_MAX = 32, 40


def toy_world():
    g = torch.Generator().manual_seed(123)
    return {
        "motion_centres": torch.randn(CLASSES, D, generator=g),
        "caption_centres": torch.randn(CLASSES, DS, generator=g),
        "paraphrases": 0.1 * torch.randn(CLASSES, 3, DS, generator=g),  # 3 captions per class
    }


def toy_items(world, classes, seed):
    """One item per class in `classes`: frames = the class's centre + noise, a random length
    (padding zeros), one of the class's captions."""
    g = torch.Generator().manual_seed(seed)
    items = []
    for c in classes.tolist():
        n = int(torch.randint(8, T_MAX + 1, (1,), generator=g))
        motion = torch.zeros(T_MAX, D)
        motion[:n] = world["motion_centres"][c] + 0.7 * torch.randn(n, D, generator=g)
        sentence = (
            world["caption_centres"][c] + world["paraphrases"][c, int(torch.randint(0, 3, (1,), generator=g))]
        )
        items.append(
            {"motion": motion, "lengths": torch.tensor(n), "sentence": sentence, "cls": torch.tensor(c)}
        )
    return items


@pytest.mark.slow
def test_module_learns_toy_retrieval_and_checkpoint_loads_weights_only(tmp_path):
    L.seed_everything(0)
    world = toy_world()
    g = torch.Generator().manual_seed(0)
    train = toy_items(world, torch.randint(0, CLASSES, (4096,), generator=g), seed=1)
    # Validation batches of 32 hold one item of each class, so pairs differ only by class.
    val = [
        item
        for k in range(4)
        for item in toy_items(world, torch.randperm(CLASSES, generator=g), seed=100 + k)
    ]
    mean, std = torch.randn(D), torch.rand(D) + 0.5
    module = ContrastiveEvaluatorModule(
        D,
        DS,
        {"embed_dim": 32, "hidden_dim": 32, "text_hidden_dim": 64, "dropout": 0.0},
        {"lr": 3e-3, "betas": [0.9, 0.999], "weight_decay": 0.01, "warmup_steps": 10},
        {"false_negative_threshold": 0.95},
        mean=mean,
        std=std,
        text_encoder={"name": "fake", "identity": "fake-0"},
        data={"name": "toy", "fingerprint": "f" * 16},
    )
    val_loader = torch.utils.data.DataLoader(val, batch_size=32)
    batch = next(iter(val_loader))
    with torch.no_grad():  # untrained: about chance (1/32)
        t2m, _ = matching_ranks(
            *reversed(module.evaluator(batch["motion"], batch["lengths"], batch["sentence"]))
        )
    assert float((t2m == 0).float().mean()) < 0.25
    trainer = L.Trainer(
        accelerator="cpu",
        max_steps=300,
        val_check_interval=300,
        check_val_every_n_epoch=None,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
    )
    trainer.fit(module, torch.utils.data.DataLoader(train, batch_size=64, shuffle=True), val_loader)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    assert metrics["val/t2m_top1"] >= 0.9 and metrics["val/m2t_top1"] >= 0.9
    assert metrics["val/t2m_top5"] >= 0.99 and metrics["val/m2t_top5"] >= 0.99
    assert (
        metrics["val/loss"] < 0.1
    )  # measured over seeds 0-3: top-1 1.0 both ways, loss 0.001, temperature 0.062
    assert 1 / 100 <= metrics["train/temperature"] < 0.07  # learned: sharper than it started

    path = tmp_path / "evaluator.ckpt"
    trainer.save_checkpoint(path)
    ckpt = torch.load(path, weights_only=True)
    hp = ckpt["hyper_parameters"]
    assert hp["feature_dim"] == D and hp["sentence_dim"] == DS and hp["model"]["hidden_dim"] == 32
    assert hp["text_encoder"]["identity"] == "fake-0" and hp["loss"]["false_negative_threshold"] == 0.95
    evaluator, info = load_contrastive_evaluator(path)
    assert not evaluator.training
    assert (
        info["text_encoder"] == {"name": "fake", "identity": "fake-0"}
        and info["data_fingerprint"] == "f" * 16
    )
    assert torch.equal(info["mean"], mean) and torch.equal(info["std"], std)
    module.eval()
    with torch.no_grad():
        assert torch.allclose(
            evaluator.embed_motions(batch["motion"], batch["lengths"]),
            module.evaluator.embed_motions(batch["motion"], batch["lengths"]),
            atol=1e-6,
        )
        assert torch.allclose(
            evaluator.embed_sentences(batch["sentence"]),
            module.evaluator.embed_sentences(batch["sentence"]),
            atol=1e-6,
        )

    # Raw features and caption strings through the stored statistics and a (fake) text encoder.
    class FakeEncoder:
        identity = "fake-0"

        def encode(self, texts):
            rows = torch.stack([world["caption_centres"][int(t.split()[-1])] for t in texts])
            return TextEmbedding(
                rows, torch.zeros(len(texts), 1, 1), torch.ones(len(texts), 1, dtype=torch.bool), 0
            )

    embedder = EvaluatorEmbedder(evaluator, info, text_encoder=FakeEncoder())
    raw = batch["motion"] * std + mean
    with torch.no_grad():
        expected = evaluator.embed_motions(batch["motion"], batch["lengths"])
    assert torch.allclose(embedder.embed_motions(raw, batch["lengths"]), expected, atol=1e-4)
    assert torch.allclose(embedder.embed_motions(raw.numpy(), batch["lengths"].tolist()), expected, atol=1e-4)
    texts = embedder.embed_texts([f"class {c}" for c in range(CLASSES)])
    nearest = torch.cdist(texts, embedder.embed_motions(raw, batch["lengths"])).argmin(1)
    assert float((batch["cls"][nearest] == torch.arange(CLASSES)).float().mean()) >= 0.9
    other = FakeEncoder()
    other.identity = "other-1"
    with pytest.raises(ValueError, match="fake-0"):
        EvaluatorEmbedder(evaluator, info, text_encoder=other)
    with pytest.raises(ValueError, match="not a contrastive evaluator checkpoint"):
        torch.save({"hyper_parameters": {"model": {}}, "state_dict": {}}, tmp_path / "other.ckpt")
        load_contrastive_evaluator(tmp_path / "other.ckpt")


# ----------------------------------------------------------------------------- end to end

ACTIONS = [
    "a person walks forward",
    "someone jumps in place",
    "a man waves his right hand",
    "the person squats down",
]


def write_action_dataset(root):
    """96 clips of 4 'actions' (each visible in the features) with 2 captions each; splits 48/8/40."""
    from tests.helpers import write_dataset

    rng = np.random.default_rng(0)
    clips, ids = {}, []
    for i in range(96):
        action = i % len(ACTIONS)
        frames = int(rng.integers(40, 90))
        features = (rng.normal(size=(frames, 263)) * 0.3 + np.linspace(-1, 1, 263) * (action - 1.5)).astype(
            np.float32
        )
        words = " ".join(f"{w}/X" for w in ACTIONS[action].split())
        lines = [f"{ACTIONS[action]}#{words}#0.0#0.0", f"{ACTIONS[action]} twice#{words} twice/X#0.0#0.0"]
        clips[f"{i:06d}"] = (features, lines)
        ids.append(f"{i:06d}")
    write_dataset(root, clips, {"train": ids[:48], "val": ids[48:56], "test": ids[56:]})
    return root


@pytest.mark.slow
def test_train_evaluator_end_to_end_is_tracked_and_registered(tmp_path):
    from mmm.fingerprint import dataset_fingerprint
    from mmm.resolve import resolve_checkpoint
    from mmm.text import CaptionEmbeddingCache
    from mmm.training.configs import load_evaluator_config
    from mmm.training.evaluator import register_evaluator, train_evaluator

    root = write_action_dataset(tmp_path / "ds")
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    overrides = {
        "data.root": root,
        "data.synthesize": "null",
        "data.batch_size": 16,
        "model.hidden_dim": 16,
        "model.embed_dim": 32,
        "model.text_hidden_dim": 32,
        "trainer.max_steps": 6,
        "trainer.val_check_interval": 3,
        "trainer.log_every_n_steps": 1,
        "trainer.enable_progress_bar": "false",
        "output_dir": f"{tmp_path}/ev",
        "text.cache_dir": f"{tmp_path}/text",
        "logger.tracking_uri": uri,
        "logger.artifact_root": f"{tmp_path}/art",
        "registry.name": "test-evaluator",
    }  # the default hard negatives: every caption "<action> twice" has three count variants
    result = train_evaluator(load_evaluator_config([f"{k}={v}" for k, v in overrides.items()]))
    client = MlflowClient(uri)
    run = client.get_run(result.run_id)
    assert client.get_experiment(run.info.experiment_id).name == "mmm-evaluator"
    tags = run.data.tags
    fingerprint = dataset_fingerprint(root)
    assert (
        tags["mmm.stage"] == "evaluator"
        and tags["data.fingerprint"] == fingerprint == result.data_fingerprint
    )
    assert tags["text_encoder"].startswith("minilm-") and tags["text_encoder"] == result.text_encoder
    assert tags["evaluator.train_items"] == "48" and tags["evaluator.test_items"] == "40"
    assert (
        run.data.params["model.hidden_dim"] == "16" and run.data.params["registry.name"] == "test-evaluator"
    )
    assert run.data.params["loss.counterfactuals"] == "['count']"
    expected = {
        "train/loss",
        "train/temperature",
        "val/loss",
        "val/t2m_top1",
        "val/t2m_top5",
        "val/m2t_top1",
        "val/m2t_top5",
        "test/r_precision_top1",
        "test/r_precision_top2",
        "test/r_precision_top3",
        "test/matching_distance",
        "test/items",
        "baseline/shuffled_r_precision_top1",
        "test/counterfactual_count_first",
        "test/counterfactual_count_captions",
        "time/fit_s",
        "time/total_s",
    }
    assert expected <= set(run.data.metrics)
    assert len(client.get_metric_history(result.run_id, "train/loss")) == 6
    assert len(client.get_metric_history(result.run_id, "val/t2m_top1")) == 2
    m = run.data.metrics
    assert m["test/items"] == 32  # 40 test items: one batch of 32, the rest dropped
    assert (
        0.0 <= m["test/r_precision_top1"] <= m["test/r_precision_top2"] <= m["test/r_precision_top3"] <= 1.0
    )
    assert 0.0 < m["test/matching_distance"] <= 2.0  # unit-length embeddings
    # Each of the 40 test items has one "twice" caption; no caption names a speed.
    assert (
        m["test/counterfactual_count_captions"] == 40 and 0.0 <= m["test/counterfactual_count_first"] <= 1.0
    )
    assert "test/counterfactual_speed_first" not in m
    assert m["test/r_precision_top1"] == pytest.approx(result.metrics["test/r_precision_top1"])
    assert {f.path for f in client.list_artifacts(result.run_id)} >= {"config.yaml", "checkpoints"}
    assert {f.path for f in client.list_artifacts(result.run_id, "checkpoints")} == {
        "checkpoints/best.ckpt",
        "checkpoints/last.ckpt",
    }

    # A registered model version pointing at the run's checkpoints, tagged with what it was made from.
    assert result.registered_model == "test-evaluator" and result.model_version == "1"
    version = client.get_model_version("test-evaluator", "1")
    # An immutable copy of the checkpoint (a later resume of the run rewrites checkpoints/, never this), its
    # digest tagged.
    import hashlib

    digest = hashlib.sha256(open(result.best_checkpoint, "rb").read()).hexdigest()
    assert (
        version.source == f"runs:/{result.run_id}/registered/test-evaluator-{digest[:12]}"
        and version.run_id == result.run_id
    )
    assert version.tags["weights.sha256"] == digest
    assert (
        version.tags["data.fingerprint"] == fingerprint
        and version.tags["text_encoder"] == tags["text_encoder"]
    )
    assert version.tags["mmm.kind"] == "evaluator"
    for k in ("r_precision_top1", "r_precision_top2", "r_precision_top3", "matching_distance"):
        assert float(version.tags[f"test.{k}"]) == pytest.approx(m[f"test/{k}"], abs=1e-4)
    assert client.get_registered_model("test-evaluator").tags["mmm.kind"] == "evaluator"
    # Registering again adds a version to the existing model.
    assert register_evaluator(uri, "test-evaluator", result.run_id, {"note": "again"}).version in (2, "2")

    # The registered checkpoint resolves, loads with weights_only and is self-contained.
    _, path, run_id = resolve_checkpoint(
        "models:/test-evaluator/1",
        uri,
        "mmm-evaluator",
        f"{tmp_path}/ev",
        "evaluator",
        "",
        "evaluator",
        f"{tmp_path}/dl",
    )
    assert run_id == result.run_id and path.endswith("best.ckpt")
    evaluator, info = load_contrastive_evaluator(path)
    assert (
        info["data_fingerprint"] == fingerprint and info["text_encoder"]["identity"] == tags["text_encoder"]
    )
    assert np.allclose(info["mean"].numpy(), np.load(root / "Mean.npy")) and np.allclose(
        info["std"].numpy(), np.load(root / "Std.npy")
    )
    cache = CaptionEmbeddingCache(f"{tmp_path}/text", tags["text_encoder"])
    embedder = EvaluatorEmbedder(
        evaluator, info, caption_cache=cache
    )  # every caption is cached: no encoder is built
    assert embedder.embed_texts(ACTIONS).shape == (4, 32)
    features = torch.from_numpy(np.load(root / "new_joint_vecs" / "000056.npy"))[None]
    assert embedder.embed_motions(features, [features.shape[1]]).shape == (1, 32)


def test_an_evaluator_run_embeds_the_counterfactuals_it_uses():
    """Every caption, every kind of counterfactual of the test captions (the ranking after training),
    and of the train and val captions only the hard negatives' kinds."""
    from mmm.training.evaluator import captions_to_embed

    def split(*captions):
        return [SimpleNamespace(captions=[SimpleNamespace(text=c) for c in captions])]

    items = {
        "train": split("a person walks slowly", "someone jumps twice"),
        "val": split("the man runs quickly three times"),
        "test": split("a person squats slowly twice"),
    }
    got = captions_to_embed(items, ["count"])
    own = ["a person walks slowly", "someone jumps twice", "the man runs quickly three times"]
    own.append("a person squats slowly twice")
    assert got[:4] == sorted(own)
    variants = set(got[4:])
    assert len(got) == 4 + len(variants)  # each caption once
    assert "someone jumps once" in variants and "the man runs quickly twice" in variants  # counts
    assert "a person walks quickly" not in variants and "the man runs slowly three times" not in variants
    # the test caption's, of every kind
    assert {"a person squats quickly twice", "a person squats slowly once"} <= variants
    assert len(variants) == 3 + 3 + 4  # count variants up to four, and one speed variant of the test caption
    assert set(captions_to_embed(items, [])) == set(got[:4]) | {
        v for v in variants if v.startswith("a person squats")
    }


@pytest.mark.slow
@pytest.mark.ddp
def test_ddp_loss_contrasts_every_ranks_pairs_as_one_process_on_the_whole_batch(tmp_path, monkeypatch):
    """Two ranks with unequal shares of one batch (5 and 3 pairs; counterfactuals on one rank
    only; a paraphrase split across them): each rank's loss, and the gradients DDP averages, are
    those of one process on the whole batch; without global negatives they are not."""
    from tests.helpers import run_ddp_worker

    monkeypatch.syspath_prepend(str(Path(__file__).parent / "ddp_workers"))  # as the worker runs
    from contrastive_ddp import make_batch, make_module

    r0, r1 = run_ddp_worker("contrastive_ddp.py", tmp_path, out_dir=tmp_path, timeout=120)
    module = make_module()
    loss, _, _ = module._loss(make_batch())
    loss.backward()
    for rank in (r0, r1):
        assert rank["loss"].item() == pytest.approx(loss.item(), rel=1e-9)
        for name, p in module.named_parameters():
            torch.testing.assert_close(rank["grads"][name], p.grad, rtol=1e-7, atol=1e-10, msg=name)
    # each rank alone sees a smaller batch: a lower loss (fewer negatives), different on each rank
    assert r0["local_loss"].item() < loss.item() - 0.1 and r1["local_loss"].item() < loss.item() - 0.1

"""The part-aware transformer and upper-body editing: condition tokens, their masking in training,
batching of [lower, upper] codes, decoding with a condition, the edit itself (the lower body stays
the source's), the CLI, training configs, promotion and the bundle."""

import json

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from mmm.cli import main
from mmm.data.datasets import TokenBatchCollator
from mmm.generation.sampler import SamplingConfig, sample_tokens
from mmm.motion.parts import split_parts
from mmm.transformer.configs import CorruptionConfig
from mmm.transformer.module import MaskedTransformerModule, mask_condition
from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig
from tests.helpers import stage2_overrides, train_tiny_stage1

K, KL = 16, 12  # upper and lower codebook sizes of the toy models


def part_transformer(seed=0):
    torch.manual_seed(seed)
    cfg = TransformerConfig(embed_dim=32, num_heads=4, num_layers=2, dropout=0.0, max_tokens=12)
    return MaskedMotionTransformer(
        torch.randn(K, 8), cfg, sentence_dim=6, word_dim=5, condition_codebook=torch.randn(KL, 4)
    ).eval()


def text_batch(n, words=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    word_mask = torch.zeros(n, words, dtype=torch.bool)
    word_mask[:, :2] = True
    return torch.randn(n, 6, generator=g), torch.randn(n, words, 5, generator=g), word_mask


def test_condition_tokens_steer_the_part_aware_transformer():
    m = part_transformer()
    sentence, words, word_mask = text_batch(2)
    tokens = torch.full((2, 6), K + 2)  # all MASK
    tokens[:, 5] = K
    lower = torch.tensor([[1, 2, 3, 4, 5, KL], [5, 4, 3, 2, 1, KL]])
    logits = m(tokens, sentence, words, word_mask, condition=lower)
    assert logits.shape == (2, 6, K) and torch.isfinite(logits).all()
    other = m(tokens, sentence, words, word_mask, condition=lower.flip(0))
    assert not torch.allclose(logits, other)  # the lower body changes the prediction
    hidden = torch.where(
        torch.arange(6) < 5, torch.full_like(lower, KL + 2), lower
    )  # every lower code masked
    assert torch.allclose(
        m(tokens, sentence, words, word_mask, condition=hidden),
        m(tokens, sentence, words, word_mask, condition=hidden.flip(0)),
    )
    with pytest.raises(ValueError, match="needs the lower-body condition"):
        m(tokens, sentence, words, word_mask)
    with pytest.raises(ValueError, match="shape of the tokens"):
        m(tokens, sentence, words, word_mask, condition=lower[:, :4])
    plain = MaskedMotionTransformer(
        torch.randn(K, 8), TransformerConfig(embed_dim=32, num_heads=4, num_layers=2, max_tokens=12), 6, 5
    )
    with pytest.raises(ValueError, match="not part-aware"):
        plain(tokens, sentence, words, word_mask, condition=lower)
    # The frozen lower codebook is a buffer, its specials and projection are trained.
    names = {n for n, _ in m.named_parameters()}
    assert (
        "condition.codebook" not in names and {"condition.special.weight", "condition.proj.weight"} <= names
    )


def test_mask_condition_hides_a_uniform_share_of_real_codes_only():
    g = torch.Generator().manual_seed(0)
    B, M = 4000, 12
    lengths = torch.randint(1, M, (B,), generator=g)
    lower = torch.full((B, M), KL + 1)
    for i, n in enumerate(lengths.tolist()):
        lower[i, :n] = torch.randint(0, KL, (n,), generator=g)
        lower[i, n] = KL
    out = mask_condition(lower, lengths, 1.0, KL + 2, g)
    real = torch.arange(M)[None] < lengths[:, None]
    assert torch.equal(out[~real], lower[~real])  # END and PAD untouched
    share = ((out == KL + 2) & real).sum(1).float() / lengths
    assert abs(share.mean().item() - 0.5) < 0.02  # U(0, 1): half on average
    assert (share == 0).any() and (share == 1).any()  # both ends of the range occur
    assert torch.equal(mask_condition(lower, lengths, 0.0, KL + 2, g), lower)
    half = mask_condition(lower, lengths, 0.5, KL + 2, g)
    assert ((half == KL + 2).sum(1).float() / lengths).max() <= 0.5 + 1e-6


def test_module_trains_upper_codes_given_the_lower_ones():
    module = MaskedTransformerModule(
        torch.randn(K, 8),
        TransformerConfig(embed_dim=32, num_heads=4, num_layers=2, dropout=0.0, max_tokens=12),
        {"warmup_steps": 0},
        CorruptionConfig(),
        6,
        5,
        condition_codebook=torch.randn(KL, 4),
    )
    assert module.hparams["condition_codebook_shape"] == [KL, 4]
    sentence, words, word_mask = text_batch(2)
    tokens = torch.stack((torch.randint(0, KL, (2, 12)), torch.randint(0, K, (2, 12))), dim=-1)
    tokens[0, 5:] = torch.tensor([K + 1, K + 1])
    tokens[0, 5] = torch.tensor([KL, K])
    tokens[1, 11] = torch.tensor([KL, K])
    batch = {
        "tokens": tokens,
        "lengths": torch.tensor([5, 11]),
        "sentence": sentence,
        "words": words,
        "word_mask": word_mask,
    }
    targets, condition = module.targets_and_condition(batch, torch.Generator().manual_seed(0))
    assert torch.equal(targets, tokens[..., 1])
    visible = condition != module.transformer.condition.mask_id
    assert torch.equal(condition[visible], tokens[..., 0][visible])
    with pytest.raises(ValueError, match=r"\(B, M, 2\) tokens"):
        module.targets_and_condition({**batch, "tokens": tokens[..., 1]})


def test_collator_pads_lower_and_upper_codes():
    class Cache:
        def lookup(self, captions):
            from mmm.text import TextEmbedding

            n = len(captions)
            return TextEmbedding(
                torch.zeros(n, 6), torch.zeros(n, 2, 5), torch.ones(n, 2, dtype=torch.bool), 0
            )

    collate = TokenBatchCollator(Cache(), num_codes=K, max_tokens=12)
    batch = collate(
        [
            {"tokens": torch.tensor([[1, 2], [3, 4]]), "caption": "a", "name": "x"},
            {"tokens": torch.tensor([[5, 6], [7, 8], [9, 10], [11, 12]]), "caption": "b", "name": "y"},
        ]
    )
    assert batch["tokens"].shape == (2, 5, 2) and batch["lengths"].tolist() == [2, 4]
    assert batch["tokens"][0, :, 1].tolist() == [2, 4, K, K + 1, K + 1] and batch["tokens"][
        0, :, 0
    ].tolist() == [1, 3, K, K + 1, K + 1]
    assert batch["tokens"][1, 4].tolist() == [K, K]


def test_decoding_with_a_condition_is_deterministic_and_depends_on_it():
    m = part_transformer()
    sentence, words, word_mask = text_batch(2)

    from mmm.text import TextEmbedding

    text = TextEmbedding(sentence, words, word_mask, 0)
    lengths = torch.tensor([7, 11])
    lower = torch.randint(0, KL, (2, 11), generator=torch.Generator().manual_seed(1))
    run = lambda cond, seed=0: sample_tokens(  # noqa: E731
        m, text, lengths, SamplingConfig(), condition=cond, generator=torch.Generator().manual_seed(seed)
    )  # noqa: E731
    a, b = run(lower), run(lower)
    assert torch.equal(a.tokens, b.tokens)
    assert (
        ((a.tokens[0, :7] >= 0) & (a.tokens[0, :7] < K)).all()
        and a.tokens[0, 7] == K
        and (a.tokens[0, 8:] == K + 1).all()
    )
    # Another condition changes what is drawn; on this tiny random model it moves the probabilities
    # only a little, and a seed draws the same code wherever the best two p / q are not close, so over
    # several seeds.
    assert any(not torch.equal(run(lower.flip(1), seed).tokens, run(lower, seed).tokens) for seed in range(5))


# -- a trained (briefly) part-aware model ---------------------------------------------------------
@pytest.fixture
def parts_model(parts_trained):
    return parts_trained


@pytest.mark.slow
def test_part_aware_training_is_tracked_and_checked(parts_model):
    from mmm.training.configs import load_stage2_config
    from mmm.training.stage2 import prepare_stage2_data

    client = MlflowClient(parts_model["uri"])
    run = client.get_run(parts_model["stage2"].run_id)
    assert client.get_experiment(run.info.experiment_id).name == "mmm-stage2-parts"
    assert {"val/acc_masked", "train/loss"} <= set(run.data.metrics)
    ckpt = torch.load(parts_model["stage2"].best_checkpoint, map_location="cpu", weights_only=True)
    assert ckpt["hyper_parameters"]["condition_codebook_shape"] == [32, 32]
    # A whole-body stage-2 config refuses the part-aware tokenizer, and the other way round.
    out, walker = parts_model["out"], parts_model["walker"]
    with pytest.raises(ValueError, match="stage2-parts"):
        prepare_stage2_data(
            load_stage2_config(stage2_overrides(walker, out, stage1=parts_model["stage1"].best_checkpoint))
        )
    plain = train_tiny_stage1(walker, out / "plain")
    with pytest.raises(ValueError, match="train-stage1-parts"):
        prepare_stage2_data(
            load_stage2_config(stage2_overrides(walker, out, stage1=plain.best_checkpoint), parts=True)
        )


@pytest.mark.slow
def test_edit_keeps_the_source_lower_body_and_refuses_what_it_cannot_do(parts_model):
    from mmm.generation.model import TextToMotion

    model = TextToMotion.from_files(
        parts_model["stage2"].best_checkpoint, parts_model["stage1"].best_checkpoint
    )
    assert model.part_aware
    source = np.load(parts_model["walker"] / "new_joint_vecs" / "000007.npy")  # 111 frames
    out = model.edit_upper_body(source, "a person waves both hands", lower_mask=0.5, seed=0, num_samples=2)
    assert [f.shape for f in out.features] == [(108, 263)] * 2 and out.joints[0].shape == (108, 22, 3)
    assert out.kept_codes.shape == (2, 27) and out.kept_codes.sum(1).tolist() == [
        13,
        13,
    ]  # round(0.5 * 27) hidden each
    assert [c.shape for c in out.codes] == [(27, 2)] * 2
    # The lower body is the source's reconstruction through the tokenizer, exactly, whatever the
    # upper body became; so its error to the source is the tokenizer's reconstruction error.
    recon = model.decode([model.encode_motion(source)])[0]
    lower_out, _ = split_parts(out.features[1])
    lower_recon, _ = split_parts(recon)
    lower_source, _ = split_parts(source[:108])
    assert np.allclose(lower_out, lower_recon, atol=1e-5)
    assert np.abs(lower_out - lower_source).mean() == pytest.approx(
        np.abs(lower_recon - lower_source).mean(), rel=1e-4
    )
    # lower_keep shows exactly the codes of those frames; the same seed gives the same motion.
    kept = model.edit_upper_body(source, "a person waves both hands", lower_keep=[(0, 40)], seed=3)
    assert kept.kept_codes[0].tolist() == [True] * 10 + [False] * 17
    again = model.edit_upper_body(source, "a person waves both hands", lower_keep=[(0, 40)], seed=3)
    assert np.array_equal(kept.features[0], again.features[0])
    with pytest.raises(ValueError, match="whole-body model"):
        model.generate(["a person walks"], [80])
    with pytest.raises(ValueError, match="not both"):
        model.edit_upper_body(source, "a person waves", lower_mask=0.5, lower_keep=[(0, 40)])
    with pytest.raises(ValueError, match="goes past"):
        model.edit_upper_body(source, "a person waves", lower_keep=[(0, 200)])
    with pytest.raises(ValueError, match=r"expected \(T, 263\)"):
        model.edit_upper_body(source[:, :100], "a person waves")


@pytest.mark.slow
def test_cli_upper_body_edit_writes_samples_and_refuses_bad_input(parts_model, tmp_path, capsys):
    source = parts_model["walker"] / "new_joint_vecs" / "000007.npy"
    common = [
        "edit",
        "upper-body",
        "--source",
        str(source),
        "--model",
        parts_model["stage2"].best_checkpoint,
        "--tracking-uri",
        parts_model["uri"],
    ]
    assert (
        main(
            [
                *common,
                "--text",
                "a person punches with both hands",
                "--lower-mask",
                "0.25",
                "--out",
                str(tmp_path / "ok"),
            ]
        )
        == 0
    )
    meta = json.loads((tmp_path / "ok/0/meta.json").read_text())
    assert (
        meta["lower_mask"] == 0.25
        and sum(meta["kept_codes"]) == 27 - round(0.25 * 27)
        and meta["prompt"] == "a person punches with both hands"
    )
    assert (
        np.load(tmp_path / "ok/0/features.npy").shape == (108, 263)
        and (tmp_path / "ok/0/motion.gif").stat().st_size > 10000
    )
    capsys.readouterr()
    bad = [
        (["--text", "a person waves", "--keep", "0:40"], "keeps the whole lower body"),
        ([], "needs --text"),
        (["--text", "a person waves", "--lower-mask", "1.5"], "--lower-mask 1.5"),
        (["--text", "a person waves", "--lower-mask", "0.5", "--lower-keep", "0:40"], "not both"),
    ]
    for extra, message in bad:
        assert main([*common, *extra, "--out", str(tmp_path / "bad")]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()
    whole = [
        "edit",
        "inbetween",
        "--source",
        str(source),
        "--text",
        "a person turns",
        "--lower-mask",
        "0.5",
        "--out",
        str(tmp_path / "bad"),
    ]
    assert main(whole) == 2 and "are for `mmm edit upper-body`" in capsys.readouterr().err


@pytest.mark.slow
def test_promotion_registers_the_part_aware_bundle_and_editing_defaults_to_it(
    parts_model, monkeypatch, tmp_path
):
    import mlflow
    import pandas as pd

    from mmm.generation.model import TextToMotion
    from mmm.registry.configs import load_promote_config
    from mmm.registry.promote import promote

    monkeypatch.chdir(tmp_path)
    previous = mlflow.get_tracking_uri()
    common = [
        f"data.root={parts_model['walker']}",
        "data.synthesize=null",
        f"logger.tracking_uri={parts_model['uri']}",
        f"candidate={parts_model['stage2'].run_id}",
    ]
    try:
        # No labels here: upper_body/both is not measured, and an unmeasured criterion never promotes, not
        # even the first version.
        unmeasured = promote("upperbody", load_promote_config(common))
        decision = promote(
            "upperbody",
            load_promote_config(
                [*common, "criteria.upperbody=[{metric: val/acc_masked, mode: max, margin: 0.0}]"]
            ),
        )
    finally:
        mlflow.set_tracking_uri(previous)
    assert (unmeasured.promoted, unmeasured.alias) == (
        False,
        "challenger",
    ) and "upper_body/both" in unmeasured.reason
    assert (decision.promoted, decision.alias) == (True, "champion")
    with pytest.raises(ValueError, match="promote upperbody"):
        promote(
            "text2motion",
            load_promote_config(
                [
                    f"data.root={parts_model['walker']}",
                    "data.synthesize=null",
                    f"logger.tracking_uri={parts_model['uri']}",
                    f"candidate={parts_model['stage2'].run_id}",
                ]
            ),
        )
    mlflow.set_tracking_uri(previous)
    version = MlflowClient(parts_model["uri"]).get_model_version_by_alias("mmm-upperbody", "champion")
    # Tags hold the criteria's metrics only; the description all of them.
    assert (
        "metric.upper_body/both" not in version.tags
        and "metric.val/acc_masked" in version.tags
        and "val/acc_unmasked" in version.description
    )
    model = TextToMotion.load(None, tracking_uri=parts_model["uri"], parts=True)
    assert model.part_aware and model.identity["reference"] == "models:/mmm-upperbody@champion"
    # The bundle's pyfunc model: rows carry the source motion.
    from mmm.registry.bundle import TextToMotionPyfunc
    from mmm.resolve import bundle_checkpoints

    stage2, stage1, _ = bundle_checkpoints(
        "models:/mmm-upperbody@champion", parts_model["uri"], dst=tmp_path / "b"
    )
    wrapped = TextToMotionPyfunc()
    wrapped.model = TextToMotion.from_files(stage2, stage1)
    source = np.load(parts_model["walker"] / "new_joint_vecs" / "000007.npy")
    rows = wrapped.predict(
        None,
        pd.DataFrame({"text": ["a person waves both hands"], "source": [source[:80].tolist()], "seed": [1]}),
    )
    assert rows[0]["lower_mask"] == 0.5 and np.asarray(rows[0]["joints"]).shape == (80, 22, 3)
    # Best of N on an edit: with a judge (an untrained evaluator here: the plumbing, not the pick's
    # quality), each row keeps the draw of the upper body that the judge rates highest.
    from mmm.evaluation.contrastive import ContrastiveEvaluator, EvaluatorEmbedder
    from mmm.generation.best_of import judge_scores
    from mmm.generation.edits import UPPER_BODY, EditRequest, sampling_defaults
    from mmm.registry.bundle import sampling_config

    encoder = wrapped.model.text_encoder
    torch.manual_seed(0)
    evaluator = ContrastiveEvaluator(263, encoder.sentence_dim, {"hidden_dim": 8, "embed_dim": 8})
    wrapped.judge = EvaluatorEmbedder(evaluator, {"text_encoder": {"identity": encoder.identity}}, encoder)
    text = "a person waves both hands"
    best = wrapped.predict(
        None, pd.DataFrame({"text": [text], "source": [source[:80].tolist()], "seed": [1]}), {"candidates": 3}
    )[0]
    sampling = sampling_config(sampling_defaults(UPPER_BODY))  # the bundle's defaults for edits (guidance 4)
    drawn = EditRequest.parse(UPPER_BODY, text=text).run(wrapped.model, source[:80], sampling, 1, 3)
    scores = judge_scores(wrapped.judge, [text] * 3, drawn.features)
    np.testing.assert_allclose(best["scores"], scores, atol=1e-5)
    np.testing.assert_allclose(
        np.asarray(best["features"]), drawn.features[int(np.argmax(scores))], atol=1e-6
    )
    with pytest.raises(ValueError, match=r"row 0: source has shape \(80, 100\)"):
        wrapped.predict(
            None, pd.DataFrame({"text": ["a person waves"], "source": [source[:80, :100].tolist()]})
        )

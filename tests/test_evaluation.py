"""The evaluation protocol, prompt adherence, `mmm evaluate` and the ablation sweeps."""

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient
from PIL import Image

from mmm.data.humanml3d import load_items, load_stats
from mmm.evaluation.adherence import item_parts, prompt_adherence
from mmm.evaluation.configs import ProtocolConfig
from mmm.evaluation.protocol import evaluate_text_to_motion, interval, results_table
from mmm.evaluation.samples import spread
from mmm.generation.model import Generated


def test_interval_is_the_protocols_95_percent_half_width():
    mean, half = interval([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5 and half == pytest.approx(1.96 * math.sqrt(1.25) / 2)  # population std
    table = results_table({"Real": {"top1": (0.5, 0.01), "fid": (-0.0000001, 0.0)}}, "T")
    assert "| Real | 0.500 ± 0.010 | - | - | 0.000 ± 0.000 |" in table


@pytest.mark.parametrize(
    "field, value, bound",
    [("replications", 0, 1), ("batch_size", 0, 1), ("max_batches", 0, 1), ("mm_texts", -1, 0)],
)
def test_protocol_sizes_below_their_bound_are_refused_naming_the_key(field, value, bound):
    from mmm.config import ConfigError

    with pytest.raises(ConfigError) as refused:
        ProtocolConfig(**{field: value})
    assert f"protocol.{field}={value}: must be a whole number of at least {bound}" in str(refused.value)
    assert ProtocolConfig(max_batches=None, mm_texts=0).max_batches is None  # the whole split, no MM


class MeanEvaluator:
    """Embeds a motion by its mean features over its length and a text by its characters."""

    identity = "mean-evaluator"

    def __init__(self):
        self.motion_calls = 0

    def embed_texts(self, captions):
        return torch.stack(
            [
                torch.tensor(
                    [len(c.text), sum(map(ord, c.text)) % 97, c.text.count(" ")], dtype=torch.float32
                )
                for c in captions
            ]
        )

    def embed_motions(self, features, lengths):
        self.motion_calls += 1
        out = [features[i, : int(n), :3].mean(0) for i, n in enumerate(lengths)]
        return torch.stack(out).float()


class EchoModel:
    """Returns the real motion of the caption (an oracle) or a noisy copy of it."""

    unit, max_frames = 4, 196

    def __init__(self, items, noise=0.0):
        self.by_caption = {c.text: item for item in items for c in item.captions}
        self.noise = noise

    def generate(self, texts, frames, sampling=None, seed=None, check_lengths=True):
        from mmm.motion.features import recover_from_ric

        g = np.random.default_rng(seed)
        features = [
            self.by_caption[t].features[:n] + self.noise * g.normal(size=(n, 263)).astype(np.float32)
            for t, n in zip(texts, frames)
        ]
        return Generated(list(texts), features, [recover_from_ric(f) for f in features], [], [], 0)


@pytest.mark.slow
def test_protocol_structure_and_the_real_reference_row(walker_dataset):
    items, _ = load_items(walker_dataset, "train", feature_dim=263, fps=20, min_length=40)
    mean, std = load_stats(walker_dataset, 263)
    cfg = ProtocolConfig(replications=3, batch_size=8, diversity_times=10, mm_texts=0)
    evaluator = MeanEvaluator()
    oracle = evaluate_text_to_motion(EchoModel(items), evaluator, items, mean, std, cfg, progress=False)
    assert (
        evaluator.motion_calls == 3 * (len(items) // 8) * 2
    )  # real and generated, per batch, per replication
    assert len(oracle["replications"]) == 3
    gen, real = oracle["generated"], oracle["real"]
    assert math.isnan(gen["multimodality"][0])
    noisy = evaluate_text_to_motion(
        EchoModel(items, noise=0.5), MeanEvaluator(), items, mean, std, cfg, progress=False
    )
    assert noisy["real"] == real  # the reference row does not depend on the model
    # Echoing a clip of the caption (at another crop) is close to the real motion; adding noise is not.
    assert gen["fid"][0] < 0.02 * noisy["generated"]["fid"][0] and abs(real["fid"][0]) < 1e-6
    again = evaluate_text_to_motion(
        EchoModel(items, noise=0.5), MeanEvaluator(), items, mean, std, cfg, progress=False
    )
    same = lambda r: {k: v for k, v in r["generated"].items() if k != "multimodality"}  # noqa: E731 (nan != nan)
    assert same(again) == same(noisy)  # same seed, same numbers


@pytest.fixture(scope="module")
def synthetic_small(tmp_path_factory):
    from mmm.data.synthetic.generate import generate_dataset

    root = tmp_path_factory.mktemp("synth") / "ds"
    generate_dataset(root, num_clips=40, seed=5, progress=False)
    return root


class Replay(EchoModel):
    """Replays each item's own motion, in the order the items are asked for (captions repeat
    across clips, so the caption alone does not say which clip)."""

    def __init__(self, items):
        from collections import defaultdict

        self.pool = defaultdict(list)
        for item in items:
            self.pool[(item.captions[0].text, min(item.length, 196) // 4 * 4)].append(item)

    def generate(self, texts, frames, sampling=None, seed=None, check_lengths=True):
        from mmm.motion.features import recover_from_ric

        features = [self.pool[(t, n)].pop(0).features[:n] for t, n in zip(texts, frames)]
        return Generated(list(texts), features, [recover_from_ric(f) for f in features], [], [], 0)


@pytest.mark.slow
def test_prompt_adherence_separates_an_oracle_from_a_model_that_stands_still(synthetic_small):
    items, _ = load_items(synthetic_small, "train", feature_dim=263, fps=20, min_length=40)
    oracle = prompt_adherence(Replay(items), synthetic_small, items)
    assert oracle["count"] > 40 and oracle["rate"] >= 0.95
    stand_item = next(
        i
        for i in items
        if item_parts(
            i, __import__("json").loads((synthetic_small / "labels" / f"{i.motion_id}.json").read_text())
        )[0]["action"]
        == "stand"
    )

    class StandStill(EchoModel):
        def generate(self, texts, frames, sampling=None, seed=None, check_lengths=True):
            from mmm.motion.features import recover_from_ric

            features = [np.resize(stand_item.features, (n, 263)) for n in frames]
            return Generated(list(texts), features, [recover_from_ric(f) for f in features], [], [], 0)

    still = prompt_adherence(StandStill(items), synthetic_small, items)
    assert still["rate"] < 0.5 * oracle["rate"]
    assert (
        still["per_action"]["stand"][0] == still["per_action"]["stand"][1]
    )  # standing still does satisfy "stand"


def test_samples_say_whether_a_motion_follows_its_caption_and_which_condition_fails(synthetic_small):
    from mmm.evaluation.samples import _verdict
    from mmm.motion.features import recover_from_ric

    items, _ = load_items(synthetic_small, "train", feature_dim=263, fps=20, min_length=40)
    labels = {
        i.motion_id: json.loads((synthetic_small / "labels" / f"{i.motion_id}.json").read_text())
        for i in items
    }
    jump = next(i for i in items if [p["action"] for p in item_parts(i, labels[i.motion_id])] == ["jump"])
    stand = next(i for i in items if [p["action"] for p in item_parts(i, labels[i.motion_id])] == ["stand"])
    parts = item_parts(jump, labels[jump.motion_id])
    assert _verdict(recover_from_ric(jump.features), parts) == "follows it"
    still = recover_from_ric(np.resize(stand.features, (jump.length, 263)))
    verdict = _verdict(still, parts)
    assert verdict.startswith("does not follow it: jump ") and ", needs " in verdict
    # evenly over the split, the first included; mirrored copies only when there is nothing else
    originals = [i for i in items if not i.motion_id.startswith("M")]
    mirrors = [i for i in items if i.motion_id.startswith("M")]
    n = len(originals)
    assert mirrors and spread(items, 3) == [originals[0], originals[n // 3], originals[2 * n // 3]]
    assert spread(mirrors, 2) == [mirrors[0], mirrors[len(mirrors) // 2]]
    assert spread(items, 10_000) == originals


@pytest.mark.slow
def test_adherence_reports_strict_and_order_aware_figures_per_group(synthetic_small):
    items, _ = load_items(synthetic_small, "train", feature_dim=263, fps=20, min_length=40)
    oracle = prompt_adherence(Replay(items), synthetic_small, items)
    groups = oracle["groups"]
    assert set(groups) == {"single", "composition", "counts"} and groups["composition"]["count"] > 5
    assert groups["single"]["count"] + groups["composition"]["count"] == oracle["count"]
    assert 0 < groups["counts"]["count"] < oracle["count"] and groups["counts"]["strict"] >= 0.95
    # The real motions pass both checks (the order-aware one never reads the labelled boundary).
    assert groups["composition"]["strict"] >= 0.95 and groups["composition"]["ordered"] >= 0.95
    assert oracle["ordered_rate"] >= 0.95
    assert set(oracle["per_action_ordered"]) == set(oracle["per_action"])
    for key, (passed, total) in oracle["per_action_ordered"].items():
        assert total == oracle["per_action"][key][1] and passed <= total

    class Reversed(Replay):
        """Each composition played second action first: right actions, wrong order."""

        def generate(self, texts, frames, sampling=None, seed=None, check_lengths=True):
            from mmm.motion.features import recover_from_ric

            features = []
            for t, n in zip(texts, frames):
                item = self.pool[(t, n)].pop(0)
                label = json.loads((synthetic_small / "labels" / f"{item.motion_id}.json").read_text())
                parts = item_parts(item, label)
                f = item.features[:n]
                if len(parts) == 2:  # swap the pieces (features are relative to the previous frame)
                    cut = min(parts[0]["end"], n)
                    f = np.concatenate([f[cut:], f[:cut]])
                features.append(f)
            return Generated(list(texts), features, [recover_from_ric(f) for f in features], [], [], 0)

    swapped = prompt_adherence(Reversed(items), synthetic_small, items)
    assert swapped["groups"]["single"] == groups["single"]
    assert swapped["groups"]["composition"]["ordered"] < 0.5 * groups["composition"]["ordered"]


def test_item_parts_follow_the_span():
    from mmm.data.humanml3d import Caption, MotionItem

    label = {
        "parts": [
            {"action": "walk", "params": {}, "start": 0, "end": 60},
            {"action": "jump", "params": {"count": 2}, "start": 60, "end": 140},
        ]
    }
    whole = MotionItem("x", "x", np.zeros((140, 263)), [Caption("c", (), 0, 0)])
    span = MotionItem("x#60-140", "x", np.zeros((80, 263)), [Caption("c", (), 3, 7)], start=60)
    assert [(p["action"], p["start"], p["end"]) for p in item_parts(whole, label)] == [
        ("walk", 0, 60),
        ("jump", 60, 140),
    ]
    assert [(p["action"], p["start"], p["end"]) for p in item_parts(span, label)] == [("jump", 0, 80)]


@pytest.fixture(scope="module")
def own_evaluator(trained):
    from tests.helpers import train_tiny_evaluator

    return train_tiny_evaluator(trained["walker"], trained["out"], trained["uri"])


SMALL = [
    "split=train",
    "protocol.batch_size=8",
    "protocol.replications=2",
    "protocol.mm_texts=2",
    "protocol.mm_generations=3",
    "protocol.mm_times=2",
    "protocol.diversity_times=10",
    "data.synthesize=null",
]


@pytest.mark.slow
def test_mmm_evaluate_logs_the_table_to_mlflow(trained, own_evaluator, tmp_path):
    from mmm.evaluation.configs import load_evaluate_config
    from mmm.evaluation.run import evaluate

    results = evaluate(
        load_evaluate_config(
            [
                *SMALL,
                f"data.root={trained['walker']}",
                f"text2motion={trained['checkpoint']}",
                f"logger.tracking_uri={trained['uri']}",
                f"logger.artifact_root={trained['out']}/art",
                f"output_dir={tmp_path}/eval",
            ]
        )
    )
    client = MlflowClient(trained["uri"])
    run = client.get_run(results["run_id"])
    metrics = run.data.metrics
    for name in (
        "generated/top1",
        "generated/fid",
        "generated/matching_score",
        "generated/diversity",
        "generated/multimodality",
        "real/top1",
        "recon/fid",
        "recon/mpjpe_root_aligned_mm",
    ):
        assert name in metrics and np.isfinite(metrics[name]), name
        assert 0 <= metrics.get(name + "_ci", 0)
    assert abs(metrics["real/fid"]) < 1e-6
    assert (
        run.data.tags["evaluator"].startswith("contrastive-") and len(run.data.tags["data.fingerprint"]) == 16
    )
    assert {f.path for f in client.list_artifacts(results["run_id"])} >= {"evaluation.md", "evaluation.json"}
    # Four captions of the split rendered, each real motion above the model's, in the run's samples/.
    assert {f.path for f in client.list_artifacts(results["run_id"], "samples")} == {
        "samples/samples.gif",
        "samples/samples.png",
    }
    items, _ = load_items(trained["walker"], "train", feature_dim=263, fps=20, min_length=40)
    shown = spread(items, 4)
    assert len(shown) == 4 and len({i.motion_id for i in shown}) == 4
    with Image.open(tmp_path / "eval/samples.gif") as gif:
        assert gif.n_frames == max(min(i.length, 196) // 4 * 4 for i in shown)
        assert gif.width == 4 * 240
    with Image.open(tmp_path / "eval/samples.png") as sheet:
        assert sheet.size == (6 * 200, 8 * 200)  # six frames a row, a real and a generated row each
    table = (tmp_path / "eval/evaluation.md").read_text()
    assert "| Generated |" in table
    # The walker dataset has no labels: adherence, asked for by default, is said not to be measured.
    assert "adherence" not in results and not any(k.startswith("adherence") for k in metrics)
    assert results["adherence_not_measured"] == (
        f"prompt adherence not measured: {trained['walker']} has no labels/ folder (the action labels the "
        "synthetic dataset writes, which the adherence check reads)"
    )
    assert f"**Prompt adherence**: not measured: {trained['walker']} has no labels/ folder" in table
    # Asked for alone, it is refused before a run is made.
    runs = len(client.search_runs([run.info.experiment_id]))
    only = [f"data.root={trained['walker']}", f"logger.tracking_uri={trained['uri']}", "what=[adherence]"]
    with pytest.raises(ValueError, match=r"what=\[adherence\]: prompt adherence not measured: .* no labels/"):
        evaluate(load_evaluate_config(only))
    with pytest.raises(ValueError, match=r"samples=-1: give the number of captions to render, 0 for none"):
        evaluate(load_evaluate_config([*only[:2], "samples=-1"]))
    assert len(client.search_runs([run.info.experiment_id])) == runs


@pytest.mark.slow
def test_ablation_sweeps_run_as_nested_runs(trained, own_evaluator, tmp_path):
    from mmm.evaluation.ablation import run_ablation
    from mmm.evaluation.configs import load_ablation_config

    out = trained["out"]
    common = [
        *[s for s in SMALL if not s.startswith("split")],
        f"data.root={trained['walker']}",
        f"logger.tracking_uri={trained['uri']}",
        f"logger.artifact_root={trained['out']}/art",
        f"output_dir={tmp_path}/abl",
        "protocol.max_batches=1",
    ]
    result = run_ablation(
        "temperature",
        load_ablation_config(
            [*common, "split=train", f"text2motion={trained['checkpoint']}", "grids.temperature=[0.5,1.5]"]
        ),
    )
    assert list(result["rows"]) == ["temperature 0.5", "temperature 1.5"]
    rows = list(csv.DictReader(open(tmp_path / "abl/temperature/table.csv")))
    assert [r["setting"] for r in rows] == ["temperature 0.5", "temperature 1.5"] and all(
        float(r["top1"]) >= 0 for r in rows
    )
    assert (tmp_path / "abl/temperature/plot.png").stat().st_size > 5000
    # two captions drawn at each setting, under their real motions: three rows of two panels
    items, _ = load_items(trained["walker"], "train", feature_dim=263, fps=20, min_length=40)
    with Image.open(tmp_path / "abl/temperature/samples.gif") as gif:
        assert gif.width == 2 * 240 and gif.n_frames == max(
            min(i.length, 196) // 4 * 4 for i in spread(items, 2)
        )
    with Image.open(tmp_path / "abl/temperature/samples.png") as sheet:
        assert sheet.size == (6 * 200, 6 * 200)
    assert {str(tmp_path / f"abl/temperature/samples.{e}") for e in ("gif", "png")} <= set(result["files"])
    with pytest.raises(ValueError, match=r"samples=-1: give the number of captions to render, 0 for none"):
        run_ablation("temperature", load_ablation_config([*common, "samples=-1"]))
    client = MlflowClient(trained["uri"])
    experiment = client.get_experiment_by_name("mmm-ablations")
    runs = client.search_runs([experiment.experiment_id])
    parent = next(r for r in runs if r.data.tags.get("mmm.ablation") == "temperature")
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert sorted(r.data.params["setting"] for r in children) == ["temperature 0.5", "temperature 1.5"]
    assert parent.data.tags["paper.table"] == "11"
    assert {f.path for f in client.list_artifacts(parent.info.run_id, "samples")} == {
        "samples/samples.gif",
        "samples/samples.png",
    }
    # A training sweep: one stage-2 model per setting, trained and tracked in its stage's experiment.
    stage2 = [
        "trainer.max_steps=2",
        "trainer.val_check_interval=2",
        "model.transformer.embed_dim=32",
        "model.transformer.num_heads=2",
        "model.transformer.num_layers=2",
        f"output_dir={out}/abl_s2",
        f"stage1_output_dir={out}/s1",
        f"token_cache_dir={out}/tokens",
        f"text.cache_dir={out}/text",
        "callbacks.preview_captions=0",
    ]
    training = run_ablation(
        "cross-layers",
        load_ablation_config(
            [
                *common,
                "split=train",
                "grids.cross_layers=[0,2]",
                "stage2_overrides=[" + ",".join(f"'{o}'" for o in stage2) + "]",
            ]
        ),
    )
    assert list(training["rows"]) == ["0 cross-attention layers", "2 cross-attention layers"]
    sweep = client.search_runs([experiment.experiment_id], "tags.`mmm.ablation` = 'cross-layers'")[0]
    stage2_runs = client.search_runs(
        [client.get_experiment_by_name("mmm-stage2").experiment_id],
        f"attributes.run_name = 'ablation-{sweep.info.run_id[:8]}'",
    )
    assert sorted(r.data.params["model.transformer.num_cross_layers"] for r in stage2_runs) == ["0", "2"]
    # The runs trained on the sweep's data (data.root of the sweep, not given to the runs themselves).
    assert {r.data.params["data.root"] for r in stage2_runs} == {str(trained["walker"])}


@pytest.mark.slow
def test_adherence_curve_logs_fixed_captions_at_each_validation_on_rank_zero(trained, synthetic_small):
    from types import SimpleNamespace

    from mmm.callbacks.adherence import AdherenceCurve
    from mmm.generation.model import TextToMotion

    model = TextToMotion.load(str(trained["checkpoint"]), tracking_uri=trained["uri"])
    items, _ = load_items(synthetic_small, "val", feature_dim=263, fps=20, min_length=40)
    curve = AdherenceCurve(model.tokenizer, model.text_encoder, synthetic_small, items[:6], seed=3)

    class Recorder:
        def __init__(self):
            self.logged = []

        def log_metrics(self, metrics, step):
            self.logged.append((step, metrics))

    def validate(rank=0, sanity=False, step=8):
        recorder = Recorder()
        trainer = SimpleNamespace(
            is_global_zero=rank == 0, sanity_checking=sanity, loggers=[recorder], global_step=step
        )
        module = SimpleNamespace(transformer=model.transformer.train(), device=model.device)
        curve.on_validation_epoch_end(trainer, module)
        assert module.transformer.training  # the training mode is given back
        return recorder.logged

    ((step, metrics),) = validate()
    assert step == 8 and {"val_adherence/rate", "val_adherence/ordered_rate"} <= set(metrics)
    assert all(0.0 <= v <= 1.0 for v in metrics.values() if v == v)
    # The same captions and seed: the next validation of the same weights logs the same figures.
    assert validate(step=12) == [(12, metrics)]
    assert validate(rank=1) == [] and validate(sanity=True) == []


@pytest.mark.slow
def test_reconstruction_reports_whether_the_labelled_actions_survive_the_tokenizer(synthetic_small):
    from types import SimpleNamespace

    import torch

    from mmm.data.humanml3d import load_clips
    from mmm.evaluation.run import reconstruction_metrics
    from mmm.motion.skeleton import T2M_SKELETON
    from mmm.tokenizer.search import CodeSearchConfig

    clips, _ = load_clips(synthetic_small, "train", feature_dim=263, min_length=40)
    mean, std = load_stats(synthetic_small, 263)

    def stub(decode):
        network = SimpleNamespace(cfg=SimpleNamespace(downsample=4), encode=lambda x: x, decode=decode)
        return SimpleNamespace(
            tokenizer=network,
            encode=network.encode,
            encode_cfg=CodeSearchConfig(candidates=1),
            mean=torch.from_numpy(mean),
            std=torch.from_numpy(std),
            skeleton=T2M_SKELETON,
        )

    exact = reconstruction_metrics(stub(lambda z: z), None, clips, labels=synthetic_small / "labels")
    assert exact["mpjpe_root_aligned_mm"] < 1e-3 and exact["adherence"]["count"] == exact["clips"]
    assert exact["adherence"]["rate"] >= 0.95  # a lossless round trip keeps every action
    # A tokenizer that loses the motion (every frame the first one) keeps only "stand".
    frozen = reconstruction_metrics(
        stub(lambda z: z[:, :1].expand_as(z).contiguous()), None, clips, labels=synthetic_small / "labels"
    )
    assert frozen["adherence"]["rate"] < 0.5 * exact["adherence"]["rate"]
    assert set(frozen["adherence"]["per_action"]) == set(exact["adherence"]["per_action"])
    assert "adherence" not in reconstruction_metrics(stub(lambda z: z), None, clips)  # no labels given


def test_best_checkpoint_by_adherence_is_refused_where_the_curve_is_not_measured(tmp_path):
    from mmm.config import ConfigError, to_object
    from mmm.training.configs import load_stage2_config
    from mmm.training.stage2 import check_adherence_monitor

    def cfg(*extra):
        return to_object(load_stage2_config([f"data.root={tmp_path}", *extra]))

    assert check_adherence_monitor(cfg(), []) is False  # val/loss: nothing asked of the curve
    by_rate = ["callbacks.checkpoint.monitor=val_adherence/ordered_rate", "callbacks.checkpoint.mode=max"]
    assert check_adherence_monitor(cfg(*by_rate), ["an item"]) is True
    with pytest.raises(ConfigError, match=r"labels/ in data.root=.*adherence_captions > 0 \(is 0\)"):
        check_adherence_monitor(cfg(*by_rate, "callbacks.adherence_captions=0"), [])
    with pytest.raises(ConfigError, match="set callbacks.checkpoint.mode=max"):
        check_adherence_monitor(cfg(by_rate[0]), ["an item"])
    with pytest.raises(ConfigError, match="val_adherence/ordered_rate or val_adherence/rate"):
        check_adherence_monitor(cfg("callbacks.checkpoint.monitor=val_adherence/walk"), ["an item"])


@pytest.mark.slow
def test_best_checkpoint_can_be_the_most_followed_validation(synthetic_small, tmp_path):
    from mlflow.tracking import MlflowClient

    from mmm.training.configs import load_stage2_config
    from mmm.training.stage2 import train_stage2
    from tests.helpers import stage2_overrides, train_tiny_stage1

    train_tiny_stage1(synthetic_small, tmp_path)
    result = train_stage2(
        load_stage2_config(
            stage2_overrides(
                synthetic_small,
                tmp_path,
                **{
                    "trainer.max_steps": 9,
                    "callbacks.adherence_captions": 4,
                    "callbacks.preview_captions": 0,
                    "callbacks.checkpoint.monitor": "val_adherence/ordered_rate",
                    "callbacks.checkpoint.mode": "max",
                },
            )
        )
    )
    history = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db").get_metric_history(
        result.run_id, "val_adherence/ordered_rate"
    )
    assert sorted(m.step for m in history) == [3, 6, 9]
    best = torch.load(result.best_checkpoint, weights_only=True)
    (state,) = [v for k, v in best["callbacks"].items() if "val_adherence/ordered_rate" in k]
    top = max(m.value for m in history)
    assert float(state["best_model_score"]) == pytest.approx(top)
    assert best["global_step"] == min(m.step for m in history if m.value == top)


@pytest.mark.slow
def test_best_of_adherence_keeps_the_draw_the_judge_prefers(synthetic_small):
    from mmm.motion.features import recover_from_ric

    items, _ = load_items(synthetic_small, "train", feature_dim=263, fps=20, min_length=40)
    oracle = prompt_adherence(Replay(items), synthetic_small, items)
    still = next(
        i
        for i in items
        if item_parts(i, json.loads((synthetic_small / "labels" / f"{i.motion_id}.json").read_text()))[0][
            "action"
        ]
        == "stand"
    )

    def standing(n):
        return np.resize(still.features, (n, 263))

    class StillThenReal(Replay):
        """Of two candidates per caption, the first stands still and the second is the real motion."""

        feature_dim = 263

        def generate(self, texts, frames, sampling=None, seed=None, check_lengths=True):
            half = len(texts) // 2
            features = [standing(n) for n in frames[:half]]
            features += [self.pool[(t, n)].pop(0).features[:n] for t, n in zip(texts[half:], frames[half:])]
            codes = [np.zeros(n // 4, np.int64) for n in frames]
            return Generated(
                list(texts), features, [recover_from_ric(f) for f in features], codes, [1] * len(texts), 1
            )

    class MovementJudge:
        """Rates any motion above standing still (texts (1, 0); motions (1, 0) or (0, 1))."""

        info = {"feature_dim": 263}

        def sentence_embeddings(self, texts):
            raise AssertionError("not called")

        def embed_texts(self, texts):
            return torch.tensor([[1.0, 0.0]] * len(texts))

        def embed_motions(self, features, lengths):
            moves = [not np.allclose(f[:n], standing(int(n))) for f, n in zip(np.asarray(features), lengths)]
            return torch.tensor([[1.0, 0.0] if m else [0.0, 1.0] for m in moves])

    best = prompt_adherence(StillThenReal(items), synthetic_small, items, candidates=2, judge=MovementJudge())
    assert best["count"] == oracle["count"]
    assert best["rate"] == oracle["rate"] and best["groups"] == oracle["groups"]


@pytest.mark.slow
def test_mmm_evaluate_best_of_adherence_is_logged_under_its_own_keys(
    trained, own_evaluator, synthetic_small, tmp_path
):
    from mmm.evaluation.configs import load_evaluate_config
    from mmm.evaluation.run import evaluate

    common = [
        f"data.root={synthetic_small}",
        "data.synthesize=null",
        "split=train",
        "what=[adherence]",
        "adherence_max_items=6",
        f"text2motion={trained['checkpoint']}",
        f"logger.tracking_uri={trained['uri']}",
        f"logger.artifact_root={trained['out']}/art",
        f"output_dir={tmp_path}/eval",
    ]
    with pytest.raises(ValueError, match="adherence_candidates 0 is not allowed"):
        evaluate(load_evaluate_config([*common, "adherence_candidates=0"]))
    results = evaluate(
        load_evaluate_config(
            [*common, "adherence_candidates=2", f"adherence_judge={own_evaluator.best_checkpoint}"]
        )
    )
    metrics = MlflowClient(trained["uri"]).get_run(results["run_id"]).data.metrics
    assert 0.0 <= metrics["adherence_best2/ordered_rate"] <= 1.0 and "adherence/ordered_rate" not in metrics
    assert results["adherence"]["count"] == 6
    assert results["adherence_judge"]["candidates"] == 2
    assert results["adherence_judge"]["identity"].startswith("contrastive-")
    assert results["adherence_judge"]["by_clause"] is True
    assert results["adherence_judge"]["counterfactuals"] is True
    report = (tmp_path / "eval/evaluation.md").read_text()
    assert "**Prompt adherence** (best of 2 by contrastive-" in report
    assert ", clause by clause and against counterfactuals)" in report


@pytest.mark.slow
def test_cli_generate_best_of_keeps_the_top_scored_candidate(trained, own_evaluator, tmp_path, capsys):
    from mmm.cli import main

    dest = tmp_path / "gen"
    argv = ["generate", "--text", "a person walks forward", "--length", "80", "--num-samples", "2"]
    argv += ["--model", trained["checkpoint"], "--tracking-uri", trained["uri"], "--out", str(dest)]
    assert main([*argv, "--candidates", "3", "--judge", own_evaluator.best_checkpoint]) == 0, (
        capsys.readouterr().err
    )
    for k in (0, 1):
        meta = json.loads((dest / str(k) / "meta.json").read_text())
        assert meta["candidates"] == 3 and meta["judge"].startswith("contrastive-")
        assert len(meta["judge_scores"]) == 3 and all(-1 <= s <= 1 for s in meta["judge_scores"])
        assert np.load(dest / str(k) / "features.npy").shape == (80, 263)
    # The kept motion is the one its recorded score belongs to: the judge rates it at the maximum.
    from mmm.evaluation.evaluators import load_judge
    from mmm.generation.best_of import judge_scores

    judge = load_judge(own_evaluator.best_checkpoint, trained["uri"])
    kept = [np.load(dest / str(k) / "features.npy") for k in (0, 1)]
    maxima = [max(json.loads((dest / str(k) / "meta.json").read_text())["judge_scores"]) for k in (0, 1)]
    np.testing.assert_allclose(judge_scores(judge, ["a person walks forward"] * 2, kept), maxima, atol=2e-3)


@pytest.mark.slow
def test_cli_edit_best_of_judges_the_generated_frames(trained, own_evaluator, tmp_path, capsys):
    from mmm.cli import main
    from mmm.evaluation.evaluators import load_judge
    from mmm.generation.best_of import judge_scores

    source = next((Path(trained["walker"]) / "new_joint_vecs").glob("*.npy"))
    dest = tmp_path / "edit"
    argv = ["edit", "inbetween", "--source", str(source), "--keep", "0:20,60:80", "--length", "80"]
    argv += ["--text", "a person walks forward", "--model", trained["checkpoint"]]
    argv += ["--tracking-uri", trained["uri"], "--out", str(dest)]
    assert main([*argv, "--candidates", "3", "--judge", own_evaluator.best_checkpoint]) == 0, (
        capsys.readouterr().err
    )
    meta = json.loads((dest / "0" / "meta.json").read_text())
    assert meta["candidates"] == 3 and meta["judge"].startswith("contrastive-")
    assert meta["judged_frames"] == [20, 60] and len(meta["judge_scores"]) == 3
    kept = np.load(dest / "0" / "features.npy")
    assert kept.shape == (80, 263)
    # The kept draw is the one the judge rates highest on the generated frames 20:60.
    judge = load_judge(own_evaluator.best_checkpoint, trained["uri"])
    score = judge_scores(judge, ["a person walks forward"], [kept[20:60]])
    np.testing.assert_allclose(score, [max(meta["judge_scores"])], atol=2e-3)


@pytest.mark.slow
def test_cli_generate_long_best_of_records_every_segments_scores(trained, own_evaluator, tmp_path, capsys):
    from mmm.cli import main

    dest = tmp_path / "long"
    argv = ["generate-long", "--text", "a person walks forward", "--text", "a person turns left"]
    argv += ["--lengths", "40,48", "--model", trained["checkpoint"], "--tracking-uri", trained["uri"]]
    argv += ["--out", str(dest), "--candidates", "2", "--judge", own_evaluator.best_checkpoint]
    assert main(argv) == 0, capsys.readouterr().err
    meta = json.loads((dest / "0" / "meta.json").read_text())
    assert meta["candidates"] == 2 and meta["judge"].startswith("contrastive-")
    assert [len(row) for row in meta["judge_scores"]] == [2, 2]
    assert meta["segments_frames"] == [[0, 40], [48, 96]] and meta["length_frames"] == 96

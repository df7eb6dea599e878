"""The editing benchmarks (`mmm evaluate task=...`): kept ranges, the batched edit, exactness of the
kept frames, the labelled checks, long sequences, upper-body edits and the protocol refactor."""

import json
import math

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from mmm.data.humanml3d import load_items, load_stats
from mmm.evaluation.configs import EditingConfig, ProtocolConfig
from mmm.evaluation.editing import evaluate_editing, generated_spans, keep_ranges, temporal_adherence
from mmm.evaluation.protocol import evaluate_text_to_motion
from mmm.generation.sampler import SamplingConfig

QUICK = ProtocolConfig(replications=2, batch_size=8, max_batches=1, diversity_times=5, mm_texts=0)


class MeanEvaluator:
    """Embeds a motion by its mean features and a text by its characters (no model to train)."""

    identity = "mean-evaluator"

    def embed_texts(self, captions):
        return torch.tensor(
            [[len(c.text), sum(map(ord, c.text)) % 97, c.text.count(" ")] for c in captions]
        ).float()

    def embed_motions(self, features, lengths):
        return torch.stack([features[i, : int(n), :3].mean(0) for i, n in enumerate(lengths)]).float()


def test_kept_ranges_on_a_hand_checked_length():
    cfg = EditingConfig()
    assert keep_ranges("inbetween", 80, cfg) == [(0, 20), (60, 80)]
    assert keep_ranges("outpaint", 80, cfg) == [(20, 60)]
    assert keep_ranges("prefix", 80, cfg) == [(0, 40)]
    assert keep_ranges("suffix", 80, cfg) == [(40, 80)]
    # Bounds on the 4-frame grid: 25% of 36 frames is 9, rounded to 8.
    assert keep_ranges("inbetween", 36, cfg) == [(0, 8), (28, 36)]
    assert keep_ranges("outpaint", 36, cfg) == [(8, 28)]
    assert generated_spans([(0, 20), (60, 80)], 80) == [(20, 60)]
    assert generated_spans([(20, 60)], 80) == [(0, 20), (60, 80)]
    assert keep_ranges("prefix", 80, EditingConfig(prefix_keep=0.75)) == [(0, 60)]
    with pytest.raises(ValueError, match="multiple of 4 frames, at least 12"):
        keep_ranges("prefix", 8, cfg)
    with pytest.raises(ValueError, match=r"editing.inbetween_keep=0.5: .* between 0.0 and 0.5"):
        EditingConfig(inbetween_keep=0.5).validate()
    with pytest.raises(ValueError, match="lower mask 1.5"):
        EditingConfig(lower_masks=[0.0, 1.5]).validate()
    with pytest.raises(ValueError, match=r"editing.context_codes=-2: .* at least 1"):
        EditingConfig(context_codes=-2).validate()
    with pytest.raises(ValueError, match=r"editing.transition_codes=-1: .* at least 0"):
        EditingConfig(transition_codes=-1).validate()


def test_a_bad_task_name_is_an_error_naming_the_choices():
    from mmm.evaluation.configs import load_evaluate_config
    from mmm.evaluation.run import evaluate

    with pytest.raises(
        ValueError, match=r"task='inpaint' .*text2motion\|inbetween\|outpaint\|prefix\|suffix"
    ):
        evaluate(load_evaluate_config(["task=inpaint", "logger.enabled=false"]))


@pytest.fixture(scope="module")
def model(trained):
    from mmm.generation.model import TextToMotion

    return TextToMotion.load(trained["checkpoint"], trained["uri"])


@pytest.fixture(scope="module")
def walker_items(trained):
    items, _ = load_items(trained["walker"], "train", feature_dim=263, fps=20, min_length=40)
    return items


@pytest.mark.slow
def test_edit_batch_is_one_call_that_keeps_every_rows_codes(model, walker_items):
    sources = [walker_items[i].features[:n] for i, n in ((7, 96), (13, 120), (5, 60))]
    assert [len(s) for s in sources] == [96, 120, 60]
    keeps = [keep_ranges("inbetween", len(s), EditingConfig()) for s in sources]
    texts = ["a person turns", None, "a person turns"]
    greedy = SamplingConfig(temperature=0)  # argmax draws: a row does not depend on its batch
    batch = model.edit_batch(sources, keeps, texts, greedy, seed=3)
    assert [f.shape for f in batch.features] == [(96, 263), (120, 263), (60, 263)]
    for i, (source, keep, text) in enumerate(zip(sources, keeps, texts)):
        alone = model.edit(source, keep, text, sampling=greedy, seed=3)
        assert np.array_equal(alone.codes[0], batch.codes[i])
        assert np.array_equal(alone.kept_codes, batch.kept_codes[i, : len(alone.kept_codes)])
    # Sampled draws: every row keeps exactly the source's codes where asked.
    sampled = model.edit_batch(sources, keeps, texts, SamplingConfig(), seed=0)
    for source, keep, codes, kept in zip(sources, keeps, sampled.codes, sampled.kept_codes):
        mask = model.keep_mask(len(codes), keep)
        assert np.array_equal(kept[: len(codes)], mask) and mask.any() and not mask.all()
        assert np.array_equal(codes[mask], model.encode_motion(source)[mask])
    with pytest.raises(ValueError, match=r"source 1: source features have shape \(60, 22\)"):
        model.edit_batch([sources[0], np.zeros((60, 22))], keeps[:2], texts[:2])
    with pytest.raises(ValueError, match="2 sources but 1 texts"):
        model.edit_batch(sources[:2], keeps[:2], texts[:1])
    with pytest.raises(ValueError, match="source 0: every code is kept"):
        model.edit_batch(sources[:1], [[(0, 96)]], texts[:1])


@pytest.mark.slow
def test_default_producer_gives_the_numbers_of_generation(model, walker_items, trained):
    mean, std = load_stats(trained["walker"], 263)
    cfg = ProtocolConfig(replications=2, batch_size=8, max_batches=2, diversity_times=5, mm_texts=0)
    default = evaluate_text_to_motion(model, MeanEvaluator(), walker_items, mean, std, cfg, progress=False)

    def as_before(texts, lengths, real, seed):  # the call the protocol made before it took a producer
        out = model.generate(texts, lengths, cfg.sampling, seed=seed, check_lengths=False)
        return out.features

    explicit = evaluate_text_to_motion(
        model, MeanEvaluator(), walker_items, mean, std, cfg, progress=False, produce=as_before
    )
    assert default["replications"] == explicit["replications"]
    assert {k: v for k, v in default["generated"].items() if k != "multimodality"} == {
        k: v for k, v in explicit["generated"].items() if k != "multimodality"
    }


def _edit_walker(task, model, walker_items, trained, cfg, tmp_path):
    """evaluate_editing of `task` on the walker items with the quick protocol and MeanEvaluator."""
    mean, std = load_stats(trained["walker"], 263)
    return evaluate_editing(
        task,
        model,
        MeanEvaluator(),
        walker_items,
        mean,
        std,
        QUICK,
        cfg,
        trained["walker"],
        tmp_path,
        progress=False,
    )


@pytest.mark.slow
def test_temporal_task_exactness_and_intervals(model, walker_items, trained, tmp_path):
    out = _edit_walker(
        "prefix", model, walker_items, trained, EditingConfig(prefix_keep=0.75, far_frames=24), tmp_path
    )
    results, metrics = out["results"], out["metrics"]
    for metric in ("top1", "fid", "diversity", "matching_score"):
        value, ci = results["generated"][metric]
        assert math.isfinite(value) and math.isfinite(ci) and ci >= 0, metric
        assert f"edit/prefix/{metric}" in metrics and f"edit/prefix/real_{metric}" in metrics
    assert math.isnan(results["generated"]["multimodality"][0]) and "edit/prefix/multimodality" not in metrics
    exact = results["exactness"]
    assert exact["frames"] > 0 and exact["frames_far"] > 0
    # Kept codes decode like the source's own reconstruction away from the generated frames; the
    # decoder's receptive field only reaches so far (a few mm of float noise through 21 joints).
    assert exact["reconstruction_far"]["max"] < 1.0
    assert exact["reconstruction"]["mean"] <= exact["reconstruction"]["max"]
    assert metrics["edit/prefix/kept_max_mm_vs_reconstruction_far"] == exact["reconstruction_far"]["max"]
    assert "| Edited (prefix) |" in out["table"] and "kept frames of an 80-frame motion: 0:60" in out["table"]


@pytest.mark.slow
def test_temporal_task_without_text_decodes_the_unconditional_branch(
    model, walker_items, trained, tmp_path, monkeypatch
):
    seen = []
    edit_batch = model.edit_batch

    def recording(sources, kept, texts, *args, **kwargs):
        seen.extend(texts)
        return edit_batch(sources, kept, texts, *args, **kwargs)

    monkeypatch.setattr(model, "edit_batch", recording)
    out = _edit_walker("inbetween", model, walker_items, trained, EditingConfig(with_text=False), tmp_path)
    assert seen and all(t is None for t in seen)  # every edit of the protocol, none with its caption
    assert model.text_dropout == 0.1  # read from the checkpoint: its unconditional branch is trained
    metrics = out["metrics"]
    assert "edit/inbetween-without-text/fid" in metrics
    assert not any(k.startswith("edit/inbetween/") for k in metrics)
    assert out["results"]["editing"]["with_text"] is False
    assert "| Edited (inbetween, without text) |" in out["table"]
    # The kept codes are the source's with or without text.
    assert out["results"]["exactness"]["reconstruction_far"]["max"] < 1.0


@pytest.fixture(scope="module")
def synthetic_small(tmp_path_factory):
    from mmm.data.synthetic.generate import generate_dataset

    root = tmp_path_factory.mktemp("synth") / "ds"
    generate_dataset(root, num_clips=24, seed=5, progress=False)
    return root


@pytest.mark.slow
def test_labelled_checks_count_every_edit(model, synthetic_small):
    items, _ = load_items(synthetic_small, "train", feature_dim=263, fps=20, min_length=40)
    found = temporal_adherence(
        model, synthetic_small, items, "suffix", EditingConfig(), SamplingConfig(), max_items=12
    )
    assert found["count"] + found["unchecked"] == 12  # never dropped silently
    assert found["whole_count"] == 12 and 0 <= found["whole_rate"] <= 1
    assert sum(total for _, total in found["per_action"].values()) == found["count"]
    if found["count"]:
        assert found["real_rate"] >= 0.5  # the real motions do what their labels say


@pytest.mark.slow
def test_long_task_scores_segments_and_transitions(model, walker_items, trained, tmp_path):
    with pytest.raises(ValueError, match=r"long_prompts=9: .* at most protocol.batch_size=8"):
        _edit_walker("long", model, walker_items, trained, EditingConfig(long_prompts=9), tmp_path)
    out = _edit_walker("long", model, walker_items, trained, EditingConfig(long_prompts=4), tmp_path)
    smooth = out["results"]["smoothness"]
    assert all(math.isfinite(v) and v > 0 for v in smooth.values()), smooth
    assert math.isfinite(out["metrics"]["edit/long/fid"]) and "edit/long/transition_ratio" in out["metrics"]


@pytest.mark.slow
def test_mmm_evaluate_runs_an_editing_task_and_refuses_the_wrong_model(trained, tmp_path, monkeypatch):
    from mmm.evaluation import run as evaluation_run
    from mmm.evaluation.configs import load_evaluate_config

    monkeypatch.setattr(evaluation_run, "load_evaluator", lambda *args: MeanEvaluator())
    common = [
        "split=train",
        "data.synthesize=null",
        f"data.root={trained['walker']}",
        f"text2motion={trained['checkpoint']}",
        f"logger.tracking_uri={trained['uri']}",
        f"logger.artifact_root={trained['out']}/art",
        f"output_dir={tmp_path}/eval",
        "protocol.replications=2",
        "protocol.max_batches=1",
        "protocol.batch_size=8",
        "protocol.diversity_times=5",
    ]
    results = evaluation_run.evaluate(load_evaluate_config([*common, "task=outpaint"]))
    run = MlflowClient(trained["uri"]).get_run(results["run_id"])
    assert run.info.run_name.startswith("evaluate-outpaint-") and run.data.params["task"] == "outpaint"
    assert math.isfinite(run.data.metrics["edit/outpaint/fid"])
    assert "edit/outpaint/kept_mean_mm_vs_reconstruction" in run.data.metrics
    assert "| Edited (outpaint) |" in (tmp_path / "eval/evaluation.md").read_text()
    results = evaluation_run.evaluate(
        load_evaluate_config([*common, "task=prefix", "editing.with_text=false"])
    )
    run = MlflowClient(trained["uri"]).get_run(results["run_id"])
    assert run.info.run_name.startswith("evaluate-prefix-without-text-")
    assert json.loads(run.data.params["editing"])["with_text"] is False
    assert "edit/prefix-without-text/fid" in run.data.metrics
    with pytest.raises(
        ValueError, match=r"part-aware model; .* whole-body model\. Pass text2motion=models:/mmm-upperbody"
    ):
        evaluation_run.evaluate(load_evaluate_config([*common, "task=upper-body", "logger.enabled=false"]))


@pytest.fixture(scope="module")
def parts_model(parts_trained):
    """The shared tiny part-aware model, loaded."""
    from mmm.generation.model import TextToMotion

    return TextToMotion.from_files(
        parts_trained["stage2"].best_checkpoint, parts_trained["stage1"].best_checkpoint
    )


@pytest.mark.slow
def test_samples_render_each_task_beside_the_real_motions(
    model, parts_model, walker_items, trained, tmp_path
):
    """`mmm evaluate`'s samples: two walker clips, each real motion above what the task made of it."""
    from PIL import Image

    from mmm.evaluation.samples import render_samples, spread

    frames = max(min(i.length, 196) // 4 * 4 for i in spread(walker_items, 2))
    for task, which in (("text2motion", model), ("inbetween", model), ("upper-body", parts_model)):
        files = render_samples(
            which, task, walker_items, trained["walker"], tmp_path / task, 2, EditingConfig()
        )
        assert [f.name for f in files] == ["samples.gif", "samples.png"], task
        with Image.open(files[0]) as gif:
            assert (gif.width, gif.n_frames) == (2 * 240, frames), task
        with Image.open(files[1]) as sheet:
            assert sheet.size == (6 * 200, 4 * 200), task
    # none asked for: nothing written
    assert (
        render_samples(
            model, "inbetween", walker_items, trained["walker"], tmp_path / "none", 0, EditingConfig()
        )
        == []
    )
    assert not (tmp_path / "none").exists()


@pytest.mark.slow
def test_long_samples_render_one_long_motion_under_its_captions_real_motions(
    model, walker_items, trained, tmp_path
):
    from PIL import Image

    from mmm.evaluation.samples import chosen_items, render_samples

    editing = EditingConfig(long_prompts=3)
    chosen = chosen_items(model, walker_items, 3)
    files = render_samples(model, "long", walker_items, trained["walker"], tmp_path / "long", 1, editing)
    assert [f.name for f in files] == ["samples.gif", "samples.png"]
    # the same long motion as the task's generate_long call draws
    out = model.generate_long(
        [item.captions[0].text for item, _ in chosen],
        [frames for _, frames in chosen],
        None,
        0,
        editing.transition_codes,
        editing.context_codes,
        check_lengths=False,
    )
    long_frames = out.joints[0].shape[0]
    assert long_frames > max(frames for _, frames in chosen)
    with Image.open(files[0]) as gif:
        # three real motions in the top row, the long motion under them: a GIF frame per long frame
        assert (gif.width, gif.height // 240, gif.n_frames) == (3 * 240, 2, long_frames)
    with Image.open(files[1]) as sheet:
        assert sheet.size == (6 * 200, 4 * 200)  # a row per motion: three real, one long
    # fewer than two captions long enough for a long motion: nothing written
    one = render_samples(model, "long", walker_items[:1], trained["walker"], tmp_path / "one", 1, editing)
    assert one == [] and not (tmp_path / "one").exists()


@pytest.mark.slow
def test_upper_body_task_sweeps_the_lower_mask(parts_model, walker_items, trained, tmp_path):
    mean, std = load_stats(trained["walker"], 263)
    cfg = EditingConfig(lower_mask=0.5, lower_masks=[1.0])
    out = evaluate_editing(
        "upper-body",
        parts_model,
        MeanEvaluator(),
        walker_items,
        mean,
        std,
        QUICK,
        cfg,
        trained["walker"],
        tmp_path,
        progress=False,
    )
    sweep = out["results"]["sweep"]
    assert [e["lower_mask"] for e in sweep] == [0.5, 1.0]
    for e in sweep:
        assert all(math.isfinite(e["generated"][m][0]) for m in ("fid", "top1", "diversity"))
        # The lower body is the source's reconstruction, exactly, whatever the mask.
        assert e["exactness"]["reconstruction"]["max"] < 1e-2 < e["exactness"]["source"]["max"]
    assert [step for step, _ in out["series"]["edit/upper-body/sweep/fid"]] == [50, 100]
    assert "edit/upper-body/fid" in out["metrics"] and "lower mask 0.5 (main)" in out["table"]
    assert (
        out["artifacts"] == [tmp_path / "upper_body_lower_mask.png"]
        and out["artifacts"][0].stat().st_size > 0
    )
    with pytest.raises(ValueError, match="task=inbetween needs a whole-body model"):
        evaluate_editing(
            "inbetween",
            parts_model,
            MeanEvaluator(),
            walker_items,
            mean,
            std,
            QUICK,
            cfg,
            trained["walker"],
            tmp_path,
        )

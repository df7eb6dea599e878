"""What a reviewer of training runs relies on in the MLflow dashboard, checked through the client:
names that say what a run is, the config logged once, one name per quantity, curves with enough
points, previews as images with a step, and lineage (git commit, dataset input, stage-1 run and
registered version)."""

import re
import subprocess
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from tests.helpers import stage2_overrides, train_tiny_stage1


@pytest.fixture(scope="module")
def stage1_runs(walker_dataset, tmp_path_factory):
    """Two short stage-1 runs with previews (validation every 2 of 4 steps), and one stage-2 run on
    the registered first one."""
    import os

    from mmm.registry.versions import TOKENIZER, register_version
    from mmm.training.configs import load_stage2_config
    from mmm.training.stage2 import train_stage2

    out = tmp_path_factory.mktemp("dashboard")
    previous = os.environ.get("MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL")
    os.environ["MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL"] = "1"
    try:
        extra = [
            "refine.steps=0",  # the 4 steps and 2 validations the tests below count
            "trainer.val_check_interval=2",
            "callbacks.preview_clips=2",
            "callbacks.usage_plot=true",
            "trainer.log_every_n_steps=1",
        ]
        first = train_tiny_stage1(walker_dataset, out, *extra)
        second = train_tiny_stage1(walker_dataset, out, *extra)
    finally:
        if previous is None:
            os.environ.pop("MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL")
        else:
            os.environ["MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL"] = previous
    uri = f"sqlite:///{out}/mlflow.db"
    client = MlflowClient(uri)
    version = register_version(client, TOKENIZER, f"runs:/{first.run_id}/checkpoints", first.run_id, {})
    client.set_registered_model_alias(TOKENIZER, "champion", version.version)
    stage2 = train_stage2(
        load_stage2_config(
            stage2_overrides(
                walker_dataset,
                out,
                **{
                    "stage1": "models:/mmm-tokenizer@champion",
                    "trainer.max_steps": 2,
                    "trainer.val_check_interval": 2,
                    "callbacks.preview_captions": 1,
                },
            )
        )
    )
    return {
        "client": client,
        "first": first,
        "second": second,
        "stage2": stage2,
        "version": version,
        "data": walker_dataset,
    }


@pytest.mark.slow
def test_runs_are_named_for_what_they_are(stage1_runs):
    client = stage1_runs["client"]
    names = [client.get_run(stage1_runs[k].run_id).info.run_name for k in ("first", "second", "stage2")]
    assert re.fullmatch(r"stage1-custom-synthetic-\d{8}-\d{6}", names[0]) and re.fullmatch(
        r"stage2-custom-synthetic-\d{8}-\d{6}", names[2]
    ), names
    assert (
        len(set(names)) == 3 or names[0] != names[2]
    )  # two runs in the same second may share a name, never a random one
    experiment = client.get_experiment(client.get_run(stage1_runs["first"].run_id).info.experiment_id)
    assert (
        experiment.tags["mlflow.experimentKind"] == "custom_model_development"
        and "tokenizer" in experiment.tags["mlflow.note.content"]
    )


def test_run_names_say_the_sizes():
    from mmm.training.common import model_label, run_name
    from mmm.training.configs import load_stage1_config

    assert model_label(load_stage1_config([]).model) == "tiny"
    assert model_label(load_stage1_config(["model=paper"]).model) == "paper"
    assert model_label(load_stage1_config(["model.tokenizer.width=16"]).model) == "custom"
    assert re.fullmatch(
        r"stage1-tiny-synthetic-\d{8}-\d{6}", run_name("stage1", "synthetic", load_stage1_config([]).model)
    )


@pytest.mark.slow
def test_the_config_is_logged_once_with_only_the_groups_a_stage_uses(stage1_runs, tmp_path):
    from mmm.training.common import flatten_config
    from mmm.training.configs import load_stage1_config

    client = stage1_runs["client"]
    params = client.get_run(stage1_runs["first"].run_id).data.params
    assert not [k for k in params if "/" in k]  # no second spelling (optim/lr beside optim.lr)
    assert not [k for k in params if k.startswith("model.transformer.")]
    assert params["optim.lr"] == str(load_stage1_config([]).optim.lr) and "normalization.statistics" in params
    import mlflow
    from omegaconf import OmegaConf

    logged = OmegaConf.load(
        mlflow.artifacts.download_artifacts(
            run_id=stage1_runs["first"].run_id,
            artifact_path="config.yaml",
            tracking_uri=client._tracking_client.tracking_uri,
            dst_path=str(tmp_path),  # not a temporary folder of its own, which nothing would remove
        )
    )
    assert params == flatten_config(logged, exclude=("model.transformer",))
    stage2 = client.get_run(stage1_runs["stage2"].run_id).data.params
    assert not [k for k in stage2 if k.startswith(("model.tokenizer.", "stage1")) or "/" in k]


@pytest.mark.slow
def test_curves_one_name_per_quantity(stage1_runs):
    client = stage1_runs["client"]
    run = client.get_run(stage1_runs["first"].run_id)
    names = set(run.data.metrics)
    assert {
        "val/mpjpe_root_aligned_mm",
        "val/mpjpe_global_mm",
        "collapse/window_active_fraction",
        "codebook/used_since_reset_fraction",
        "codebook/codes_reset_total",
        "train/lr",
    } <= names
    assert not names & {
        "val/mpjpe_mm",
        "collapse/active_fraction",
        "codebook/active_fraction",
        "codebook/codes_reset",
    }
    assert (
        len(client.get_metric_history(run.info.run_id, "val/mpjpe_root_aligned_mm")) == 2
    )  # one per validation
    assert len(client.get_metric_history(run.info.run_id, "train/lr")) >= 4
    assert any(k.startswith("system/") for k in names), sorted(names)  # MLflow's system metrics sampler


def test_the_demo_validates_ten_times():
    from mmm.training.configs import load_stage1_config, load_stage2_config

    for cfg in (load_stage1_config([]), load_stage2_config([])):
        assert cfg.trainer.max_steps // cfg.trainer.val_check_interval >= 10


@pytest.mark.slow
def test_previews_are_images_with_a_step(stage1_runs):
    client = stage1_runs["client"]
    for key, run in (("reconstruction", stage1_runs["first"]), ("generation", stage1_runs["stage2"])):
        images = [f.path for f in client.list_artifacts(run.run_id, "images")]
        steps = {int(m.group(1)) for p in images if (m := re.search(rf"previews~{key}\+step\+(\d+)\+", p))}
        assert steps == ({2, 4} if key == "reconstruction" else {2}), images
        gifs = [f.path for f in client.list_artifacts(run.run_id, "previews")]
        assert any(p.endswith(".gif") for p in gifs)


def test_a_preview_shows_reference_above_output_with_caption_and_step(tmp_path):
    import numpy as np

    from mmm.render import contact_sheet, frames
    from tests.helpers import turning_walker

    walker = turning_walker(frames=40).numpy()
    grid = frames(
        [walker, walker, walker, walker],
        ["step 7 · reference", "step 7 · reference", "step 7 · generated", "step 7 · generated"],
        size=(120, 120),
        columns=2,
    )
    assert grid[0].size == (240, 240) and len(grid) == 40  # 2 columns, references in the top row
    sheet = contact_sheet(
        [walker, walker], ["step 7 · reference: a", "step 7 · generated: a"], num_frames=6, size=(160, 160)
    )
    assert sheet.size == (960, 320)
    pixels = np.asarray(sheet)
    assert (pixels[:20] != pixels[0, 0]).any()  # the caption is drawn across the top of each row


@pytest.mark.slow
def test_lineage_git_commit_dataset_input_and_stage1_version(stage1_runs):
    from mmm.fingerprint import dataset_fingerprint

    client = stage1_runs["client"]
    checkout = Path(__file__).resolve().parents[1]  # the package's, not the working directory's
    commit = subprocess.run(
        ["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    assert len(commit) == 40
    fingerprint = dataset_fingerprint(stage1_runs["data"])
    for key in ("first", "stage2"):
        run = client.get_run(stage1_runs[key].run_id)
        assert run.data.tags["mlflow.source.git.commit"] == commit
        assert run.data.tags["mlflow.source.name"] == f"mmm train {run.data.tags['mmm.stage']}"
        inputs = run.inputs.dataset_inputs
        assert [i.dataset.digest for i in inputs] == [fingerprint] and inputs[0].dataset.name == "synthetic"
    stage2 = client.get_run(stage1_runs["stage2"].run_id)
    assert stage2.data.tags["stage1.version"] == f"mmm-tokenizer/{stage1_runs['version'].version}"
    assert stage2.data.tags["stage1.run_id"] == stage1_runs["first"].run_id
    links = re.findall(r"#/experiments/(\w+)/runs/(\w+)", stage2.data.tags["mlflow.note.content"])
    assert links and all(client.get_run(r).info.experiment_id == e for e, r in links)
    assert (
        f"#/models/mmm-tokenizer/versions/{stage1_runs['version'].version}"
        in stage2.data.tags["mlflow.note.content"]
    )


def test_perplexity_ratio_is_against_the_peak_after_warm_up():
    import torch

    from mmm.callbacks.codebook import CollapseMonitor

    class Quantizer:
        latest_counts = torch.ones(8)

    class Module:
        quantizers = {"": Quantizer()}
        last_perplexities = {"": 8.0}
        logged = {}

        def log_dict(self, metrics, **kwargs):
            self.logged.update(metrics)

    class Strategy:
        @staticmethod
        def reduce_boolean_decision(decision, all=True):
            return decision

    class Trainer:
        global_step, strategy, is_global_zero, loggers = 0, Strategy(), True, []
        fast_dev_run, log_every_n_steps, should_stop = False, 1, False  # every step is a logged one

    monitor, module, trainer = (
        CollapseMonitor(warmup_steps=5, window_steps=2, smoothing=0.0),
        Module(),
        Trainer(),
    )
    for step in range(12):
        trainer.global_step = step
        module.last_perplexities[""] = (
            8.0 if step < 5 else 4.0
        )  # the freshly seeded codebook, then a healthy one
        monitor.on_train_batch_end(trainer, module, None, None, step)
    assert module.logged["collapse/perplexity_ratio"] == pytest.approx(1.0)

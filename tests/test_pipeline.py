"""The full pipeline end to end on a small synthetic dataset: one parent MLflow run with a nested
run per step, champions promoted, generation defaulting to the champion, unchanged steps skipped
on a rerun, and --force rerunning a step and what depends on it."""

import json
import time

import numpy as np
import pytest
from mlflow.tracking import MlflowClient
from PIL import Image

from mmm.cli import main
from mmm.pipeline.steps import PIPELINES
from tests.helpers import PIPELINE_TINY as TINY
from tests.helpers import newest_parent, pipeline_args, steps_of


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("pipeline")


def pipeline(workdir, monkeypatch, *extra):
    """`mmm pipeline full` in `workdir` (relative outputs land there); returns its exit code."""
    import mlflow

    monkeypatch.chdir(workdir)
    argv = ["pipeline", "full", *pipeline_args(workdir, f"sqlite:///{workdir}/mlflow.db"), *extra]
    previous = mlflow.get_tracking_uri()
    try:
        return main(argv)
    finally:
        mlflow.set_tracking_uri(previous)  # promotion sets the process-wide store; other tests expect theirs


@pytest.mark.slow
def test_full_pipeline_trains_evaluates_promotes_and_generates(workdir, monkeypatch, capsys):
    started = time.perf_counter()
    assert pipeline(workdir, monkeypatch) == 0
    print(f"[pipeline] full, first run: {time.perf_counter() - started:.1f} s")
    out = capsys.readouterr().out
    client = MlflowClient(f"sqlite:///{workdir}/mlflow.db")
    parent = newest_parent(client)
    assert parent.info.status == "FINISHED"
    steps = steps_of(client, parent)
    assert set(steps) == set(PIPELINES["full"])
    assert all(r.data.tags["step.status"] == "ran" and r.info.status == "FINISHED" for r in steps.values())
    summary = client.download_artifacts(parent.info.run_id, "steps.txt", str(workdir))
    assert [line.split()[0] for line in open(summary)] == PIPELINES["full"]

    # Every step's own run is in its experiment, linked from the step's run.
    for step, experiment in (
        ("evaluator", "mmm-evaluator"),
        ("stage1", "mmm-stage1"),
        ("stage2", "mmm-stage2"),
        ("length", "mmm-length"),
        ("evaluate", "mmm-evaluation"),
    ):
        run = client.get_run(steps[step].data.tags["output.run_id"])
        assert (
            client.get_experiment(run.info.experiment_id).name == experiment and run.info.status == "FINISHED"
        )

    # Three champions, measured on the same data; the text-to-motion one with the champion evaluator.
    champions = {
        name: client.get_model_version_by_alias(name, "champion")
        for name in ("mmm-evaluator", "mmm-tokenizer", "mmm-text2motion")
    }
    fingerprint = champions["mmm-tokenizer"].tags["data.fingerprint"]
    assert len(fingerprint) == 16 and champions["mmm-text2motion"].tags["data.fingerprint"] == fingerprint
    assert champions["mmm-text2motion"].tags["evaluator"].startswith("contrastive-")
    # Its bundle carries that evaluator as the judge of best of N (the `candidates` param).
    text2motion = champions["mmm-text2motion"].tags
    assert text2motion["judge.identity"] == text2motion["evaluator"]
    assert champions["mmm-text2motion"].run_id == steps["stage2"].data.tags["output.run_id"]
    assert champions["mmm-tokenizer"].run_id == steps["stage1"].data.tags["output.run_id"]
    assert np.isfinite(float(champions["mmm-text2motion"].tags["metric.generated/fid"]))
    assert float(champions["mmm-tokenizer"].tags["metric.recon/mpjpe_root_aligned_mm"]) > 0
    assert "promote-text2motion" in out and "no champion yet" in out
    # Stage 2 was trained on the tokenizer champion's tokens.
    stage2 = client.get_run(champions["mmm-text2motion"].run_id)
    assert stage2.data.tags["stage1.reference"] == "models:/mmm-tokenizer@champion"
    # Its promotion rendered test captions under their real motions into its run, and says where.
    logged = {f.path for f in client.list_artifacts(stage2.info.run_id, "promotion")}
    assert logged == {"promotion/samples.gif", "promotion/samples.png"}
    gif = Image.open(client.download_artifacts(stage2.info.run_id, "promotion/samples.gif", str(workdir)))
    assert gif.n_frames > 10 and gif.width > gif.height  # panels side by side, real above generated
    assert "`promotion/samples.gif` of its run" in champions["mmm-text2motion"].description

    # Generation defaults to the champion bundle.
    code = main(
        [
            "generate",
            "--text",
            "a person walks forward",
            "--length",
            "48",
            "--tracking-uri",
            f"sqlite:///{workdir}/mlflow.db",
            "--out",
            str(workdir / "gen"),
        ]
    )
    assert code == 0
    meta = json.loads((workdir / "gen/0/meta.json").read_text())
    assert meta["model"]["reference"] == "models:/mmm-text2motion@champion" and str(
        meta["model"]["version"]
    ) == str(champions["mmm-text2motion"].version)
    assert np.load(workdir / "gen/0/joints.npy").shape == (48, 22, 3)
    listing = capsys.readouterr()
    assert main(["models", "list", "--tracking-uri", f"sqlite:///{workdir}/mlflow.db"]) == 0
    listing = capsys.readouterr().out
    assert "mmm-text2motion:" in listing and "champion" in listing and "generated/fid=" in listing


@pytest.mark.slow
def test_rerun_skips_unchanged_steps_and_force_reruns_what_depends(workdir, monkeypatch):
    client = MlflowClient(f"sqlite:///{workdir}/mlflow.db")
    versions = {
        name: len(client.search_model_versions(f"name='{name}'"))
        for name in ("mmm-evaluator", "mmm-tokenizer", "mmm-text2motion")
    }

    started = time.perf_counter()
    assert pipeline(workdir, monkeypatch) == 0
    print(f"[pipeline] full, unchanged rerun: {time.perf_counter() - started:.1f} s")
    steps = steps_of(client, newest_parent(client))
    assert {name: r.data.tags["step.status"] for name, r in steps.items()} == {
        name: "skipped" for name in PIPELINES["full"]
    }
    assert versions == {
        name: len(client.search_model_versions(f"name='{name}'")) for name in versions
    }  # nothing registered again

    # A new stage-2 run: the evaluation and the text-to-motion promotion depend on it; the
    # tokenizer, tokens, evaluator and length estimator do not.
    assert pipeline(workdir, monkeypatch, "--force", "stage2") == 0
    steps = steps_of(client, newest_parent(client))
    ran = {name for name, r in steps.items() if r.data.tags["step.status"] == "ran"}
    assert ran == {"stage2", "evaluate", "promote-text2motion"}
    assert len(client.search_model_versions("name='mmm-text2motion'")) == versions["mmm-text2motion"] + 1
    newest = max(client.search_model_versions("name='mmm-text2motion'"), key=lambda v: int(v.version))
    assert newest.run_id == steps["stage2"].data.tags["output.run_id"]
    # Trained again with the same seed on the same data: the same metrics, a tie, which is not a win.
    newest = client.get_model_version("mmm-text2motion", newest.version)
    assert newest.aliases == ["challenger"] and newest.tags["promotion"].startswith(
        "challenger: does not beat the champion"
    )
    # The same run promoted again is measured again in its own version (and bundle), never
    # registered twice.
    assert pipeline(workdir, monkeypatch, "--force", "promote-text2motion") == 0
    again = max(client.search_model_versions("name='mmm-text2motion'"), key=lambda v: int(v.version))
    assert (again.version, again.source) == (newest.version, newest.source)
    assert client.get_model_version("mmm-text2motion", again.version).aliases == ["challenger"]

    # A changed step override reruns that step (and its dependants) without --force.
    assert (
        pipeline(workdir, monkeypatch, f"overrides.length=[{','.join(TINY['length'])},model.dropout=0.3]")
        == 0
    )
    steps = steps_of(client, newest_parent(client))
    assert {name for name, r in steps.items() if r.data.tags["step.status"] == "ran"} == {"length"}


@pytest.mark.slow
def test_a_failing_step_fails_the_parent_and_keeps_the_good_state(workdir, monkeypatch, capsys):
    client = MlflowClient(f"sqlite:///{workdir}/mlflow.db")
    # An evaluation override that cannot be applied is refused before the first step runs: no new
    # pipeline run, the state file as it was.
    parents = len(client.search_runs([newest_parent(client).info.experiment_id]))
    state_before = (workdir / "state.json").read_bytes()
    evaluate = ",".join(TINY["evaluate"])
    assert pipeline(workdir, monkeypatch, f"overrides.evaluate=[{evaluate},protocol.no_such_key=1]") == 2
    err = capsys.readouterr().err
    assert "overrides.evaluate" in err and "no_such_key" in err
    assert len(client.search_runs([newest_parent(client).info.experiment_id])) == parents
    assert (workdir / "state.json").read_bytes() == state_before
    # A step that fails while it runs (the evaluator it is given is not there): the step fails, the
    # steps before it are skipped.
    missing = workdir / "no-such-evaluator.ckpt"
    missing_evaluator = f"overrides.evaluate=[{evaluate},evaluator.reference={missing}]"
    assert pipeline(workdir, monkeypatch, missing_evaluator) == 2
    assert "no-such-evaluator.ckpt" in capsys.readouterr().err
    parent = newest_parent(client)
    assert parent.info.status == "FAILED"
    steps = steps_of(client, parent)
    assert (
        steps["evaluate"].info.status == "FAILED" and steps["evaluate"].data.tags["step.status"] == "failed"
    )
    assert (
        "no-such-evaluator.ckpt"
        in open(client.download_artifacts(steps["evaluate"].info.run_id, "error.txt", str(workdir))).read()
    )
    before = PIPELINES["full"][: PIPELINES["full"].index("evaluate")]
    # Length's override is back to TINY after the previous test's change: it runs again, the rest is reused.
    assert {s: steps[s].data.tags["step.status"] for s in before} == {
        s: "ran" if s == "length" else "skipped" for s in before
    }
    assert "promote-text2motion" not in steps  # nothing ran after the failure
    state = json.loads((workdir / "state.json").read_text())
    assert set(state) >= set(PIPELINES["full"])  # the state of the good runs is kept

    # Back to the good configuration: the earlier evaluation of the same inputs is still valid.
    assert pipeline(workdir, monkeypatch) == 0
    steps = steps_of(client, newest_parent(client))
    assert {r.data.tags["step.status"] for r in steps.values()} == {"skipped"}


@pytest.mark.slow
def test_parts_pipeline_trains_and_promotes_the_part_aware_model(workdir, monkeypatch):
    import mlflow

    from mmm.generation.model import TextToMotion

    tiny_parts = {
        "stage1_parts": [*TINY["stage1"], "trainer.log_every_n_steps=1"],
        "stage2_parts": TINY["stage2"],
        "promote": [*TINY["promote"], "upper_body.max_sources=4"],
    }
    argv = [
        "pipeline",
        "parts",
        *pipeline_args(workdir, f"sqlite:///{workdir}/mlflow.db"),
        *[f"overrides.{step}=[{','.join(items)}]" for step, items in tiny_parts.items()],
    ]
    monkeypatch.chdir(workdir)
    previous = mlflow.get_tracking_uri()
    try:
        assert main(argv) == 0
        client = MlflowClient(f"sqlite:///{workdir}/mlflow.db")
        experiment = client.get_experiment_by_name("mmm-pipeline")
        parent = client.search_runs(
            [experiment.experiment_id],
            "attributes.run_name LIKE 'pipeline-parts-%'",
            order_by=["attributes.start_time DESC"],
        )[0]
        steps = steps_of(client, parent)
        assert set(steps) == set(PIPELINES["parts"]) and all(
            r.data.tags["step.status"] == "ran" for r in steps.values()
        )
        stage1 = client.get_run(steps["stage1-parts"].data.tags["output.run_id"])
        assert (
            client.get_experiment(stage1.info.experiment_id).name == "mmm-stage1-parts"
            and "codebook/upper/perplexity" in stage1.data.metrics
        )
        champion = client.get_model_version_by_alias("mmm-upperbody", "champion")
        assert champion.run_id == steps["stage2-parts"].data.tags["output.run_id"]
        # Measured on the synthetic labels: 4 walking/squatting test clips x 3 upper-body prompts.
        assert (
            champion.tags["upper_body.edits"] == "12"
            and 0.0 <= float(champion.tags["metric.upper_body/both"]) <= 1.0
        )
        assert TextToMotion.load(None, tracking_uri=f"sqlite:///{workdir}/mlflow.db", parts=True).part_aware
        # The whole-body champion is untouched, and a rerun skips everything.
        assert client.get_model_version_by_alias("mmm-text2motion", "champion").run_id != champion.run_id
        assert main(argv) == 0
        parent = client.search_runs(
            [experiment.experiment_id],
            "attributes.run_name LIKE 'pipeline-parts-%'",
            order_by=["attributes.start_time DESC"],
        )[0]
        assert {r.data.tags["step.status"] for r in steps_of(client, parent).values()} == {"skipped"}
    finally:
        mlflow.set_tracking_uri(previous)


def test_stage2_trains_on_the_champion_tokenizer_only_when_it_was_measured_on_the_pipelines_data(tmp_path):
    from mmm.config import to_object
    from mmm.pipeline.configs import load_pipeline_config
    from mmm.pipeline.runner import Context
    from mmm.pipeline.steps import _stage2_options

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    client = MlflowClient(uri)
    cfg = to_object(load_pipeline_config([f"logger.tracking_uri={uri}", f"data.root={tmp_path}/data"]))
    ctx = Context(cfg, uri)
    ctx.outputs["data_fingerprint"] = {"value": "fp-of-this-data"}  # what the data step measured
    ctx.outputs["stage1"] = {"run_id": "run-of-this-pipeline"}
    # No champion yet: this pipeline's own stage-1 run.
    assert "stage1=run-of-this-pipeline" in _stage2_options(ctx)
    client.create_registered_model("mmm-tokenizer")
    version = client.create_model_version(
        "mmm-tokenizer", source=str(tmp_path), tags={"data.fingerprint": "other"}
    )
    client.set_registered_model_alias("mmm-tokenizer", "champion", version.version)
    # A champion measured on other data (a recipe with a dataset of its own): still its own run.
    assert "stage1=run-of-this-pipeline" in _stage2_options(ctx)
    client.set_model_version_tag("mmm-tokenizer", version.version, "data.fingerprint", "fp-of-this-data")
    # The champion measured on this data: the champion.
    options = _stage2_options(ctx)
    assert "stage1=models:/mmm-tokenizer@champion" in options
    assert not any(o.startswith("stage1=run-") for o in options)

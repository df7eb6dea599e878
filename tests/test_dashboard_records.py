"""What a reviewer reads in the MLflow dashboard after `mmm pipeline full`: the parent run's name and
description (the steps in order, every link leading to an existing run), its headline metrics, the
nested step runs, the registered versions' descriptions (why each has its alias), the logged bundle
marked as registered, and the evaluation run's description; all read back through MlflowClient."""

import json
import re

import pytest
from mlflow.tracking import MlflowClient

from mmm.cli import main
from mmm.pipeline.steps import PIPELINES
from mmm.registry.configs import load_promote_config
from mmm.tracking import DESCRIPTION_TAG, GIT_COMMIT_TAG, dashboard_links, git_commit
from tests.helpers import PIPELINE_TINY as TINY
from tests.helpers import newest_parent, pipeline_args, steps_of

RUN_LINK = re.compile(r"\]\(#/experiments/([^/)\s]+)/runs/([0-9a-f]+)\?workflowType=machine_learning\)")
VERSION_LINK = re.compile(r"\]\(#/models/([^/)\s]+)/versions/(\d+)\)")
KINDS = {
    "promote-evaluator": "evaluator",
    "promote-tokenizer": "tokenizer",
    "promote-text2motion": "text2motion",
}
MARGIN = 0.01  # the second text-to-motion promotion's criterion: a retrained model ties, needs 0.01 better


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """One `mmm pipeline full`; then stage 2 trained again (`--force stage2`: the same seed, a
    tie, so its version becomes challenger) and that candidate promoted once more with a margin
    (so a version's description has a champion to compare with)."""
    import mlflow

    workdir = tmp_path_factory.mktemp("dashboard")
    uri = f"sqlite:///{workdir}/mlflow.db"
    previous = mlflow.get_tracking_uri()
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(workdir)
        try:
            assert main(["pipeline", "full", *pipeline_args(workdir, uri)]) == 0
            client = MlflowClient(uri)
            parent = newest_parent(client)
            steps = steps_of(client, parent)
            assert sorted(steps) == sorted(PIPELINES["full"]), (
                parent.info.run_name,
                parent.info.status,
                sorted(steps),
                parent.data.tags.get(DESCRIPTION_TAG),
            )
            assert main(["pipeline", "full", *pipeline_args(workdir, uri), "--force", "stage2"]) == 0
            newest = newest_parent(client)
            retrained = steps_of(client, newest)["stage2"]
            criterion = f"[{{metric: generated/fid, mode: min, margin: {MARGIN}}}]"
            assert (
                main(
                    [
                        "promote",
                        "text2motion",
                        f"candidate={retrained.data.tags['output.run_id']}",
                        f"data.root={workdir}/data",
                        f"logger.tracking_uri={uri}",
                        f"logger.artifact_root={workdir}/art",
                        *TINY["promote"],
                        f"criteria.text2motion={criterion}",
                    ]
                )
                == 0
            )
        finally:
            mlflow.set_tracking_uri(
                previous
            )  # promotion sets the process-wide store; other tests expect theirs
    return {
        "client": client,
        "uri": uri,
        "parent": client.get_run(parent.info.run_id),
        "newest_parent": client.get_run(newest.info.run_id),
        "steps": steps,
        "workdir": workdir,
    }


def links_resolve(client, text: str) -> int:
    """Every run link in `text` names an existing run of that experiment; returns how many."""
    found = RUN_LINK.findall(text)
    for experiment_id, run_id in found:
        assert client.get_run(run_id).info.experiment_id == experiment_id, (experiment_id, run_id)
    return len(found)


def versions_resolve(client, text: str) -> int:
    found = VERSION_LINK.findall(text)
    for name, version in found:
        assert str(client.get_model_version(name, version).version) == version
    return len(found)


def dataset_contexts(run) -> dict[str, str]:
    """digest -> context of the run's dataset inputs."""
    return {
        d.dataset.digest: {t.key: t.value for t in d.tags}.get("mlflow.data.context")
        for d in run.inputs.dataset_inputs
    }


@pytest.mark.slow
def test_parent_run_is_named_described_in_step_order_and_its_links_resolve(records):
    client, parent = records["client"], records["parent"]
    assert parent.info.run_name.startswith("pipeline-full-") and parent.info.status == "FINISHED"
    description = parent.data.tags[DESCRIPTION_TAG]
    assert description.startswith("### Pipeline `full` finished")
    rows = [line for line in description.splitlines() if re.match(r"\| \d\d \|", line)]
    assert [int(r.split("|")[1]) for r in rows] == list(range(1, len(PIPELINES["full"]) + 1))
    for row, step in zip(rows, PIPELINES["full"]):
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[1].startswith(f"[{step}](#/experiments/") and cells[2] == "ran" and float(cells[3]) >= 0
        if step in KINDS:  # the version it registered, its alias and why
            assert VERSION_LINK.search(cells[5]) and cells[6] in ("champion", "challenger") and cells[7]
        elif step != "tokenize":  # the step's own training or evaluation run (tokenizing has none)
            assert RUN_LINK.search(cells[4]), row
    # Each nested step run and the five steps' own runs, all existing.
    assert links_resolve(client, description) == len(PIPELINES["full"]) + 5
    assert versions_resolve(client, description) == 3


@pytest.mark.slow
def test_parent_run_has_commit_dataset_and_headline_metrics(records):
    parent, steps = records["parent"], records["steps"]
    commit = git_commit()
    if commit is not None:  # a git checkout
        assert parent.data.tags[GIT_COMMIT_TAG] == commit
    assert parent.data.tags["mlflow.source.name"] == "mmm pipeline full"
    fingerprint = (
        records["client"].get_run(steps["stage1"].data.tags["output.run_id"]).data.tags["data.fingerprint"]
    )
    assert dataset_contexts(parent) == {fingerprint: "pipeline"}
    metrics = parent.data.metrics
    assert metrics["pipeline/steps_ran"] == len(PIPELINES["full"]) and metrics["pipeline/steps_skipped"] == 0
    assert metrics["pipeline/seconds"] > sum(float(s.data.metrics["seconds"]) for s in steps.values()) * 0.99
    assert any(k.startswith("stage1/val/") for k in metrics) and any(
        k.startswith("evaluator/test/") for k in metrics
    )
    assert "evaluate/generated/fid" in metrics and "evaluate/recon/mpjpe_global_mm" in metrics
    assert not any(k.endswith("_ci") for k in metrics)


@pytest.mark.slow
def test_printed_links_open_the_training_view_and_the_pipeline_run(records):
    client, parent = records["client"], records["newest_parent"]
    lines = "\n".join(dashboard_links(client, "http://127.0.0.1:5000/")).splitlines()
    experiment = parent.info.experiment_id
    assert (
        f"mmm-pipeline       http://127.0.0.1:5000/#/experiments/{experiment}/runs?workflowType=machine_learning"
        in lines
    )
    # The newest top-level run, not the last step that started inside it.
    pipeline_run = lines[lines.index(next(row for row in lines if row.startswith("mmm-pipeline"))) + 1]
    assert pipeline_run.split() == [
        "newest",
        "run",
        f"{parent.info.run_name}:",
        f"http://127.0.0.1:5000/#/experiments/{experiment}/runs/{parent.info.run_id}?workflowType=machine_learning",
    ]
    assert lines[-1] == "registered models  http://127.0.0.1:5000/#/models"


@pytest.mark.slow
def test_step_runs_are_numbered_and_link_their_own_runs(records):
    client, steps = records["client"], records["steps"]
    assert sorted(steps) == sorted(PIPELINES["full"])
    for order, step in enumerate(PIPELINES["full"], 1):
        run = steps[step]
        assert run.info.run_name == f"{order:02d}-{step}" and run.data.tags["mmm.step.order"] == str(order)
        description = run.data.tags[DESCRIPTION_TAG]
        assert description.startswith(f"Step {order:02d} of pipeline [{records['parent'].info.run_name}]")
        if step in KINDS:
            assert versions_resolve(client, description) == 1 and run.data.tags["output.alias"] in description
            assert links_resolve(client, description) == 1  # the parent
        elif step == "tokenize":
            assert links_resolve(client, description) == 1 and "ran in" in description
        else:  # the parent, and the step's own run (also kept as the output.run_id tag)
            assert links_resolve(client, description) == 2 and run.data.tags["output.run_id"] in description


@pytest.mark.slow
def test_promoted_versions_explain_their_alias(records):
    client, steps = records["client"], records["steps"]
    for step, kind in KINDS.items():
        name, number = steps[step].data.tags["output.model"], steps[step].data.tags["output.version"]
        version = client.get_model_version(name, number)
        text = version.description
        for c in getattr(load_promote_config().criteria, kind):
            assert (
                f"`{c['metric']}`" in text and f"| {c['mode']} (" in text and f"| {c['margin']:g} |" in text
            ), (name, text)
        assert (
            "promoted to `champion`" in text
            and "no champion yet" in text.lower()
            and "none (the first version promoted)" in text
        )
        assert links_resolve(client, text) == 1  # the run that made it
        assert set(version.tags) >= {
            "data.fingerprint",
            "evaluator",
            "code.version",
            "config.hash",
            "promotion",
        }
    # The pipeline's text-to-motion version: its value with the protocol's interval.
    champion = client.get_model_version_by_alias("mmm-text2motion", "champion")
    assert (
        champion.tags["evaluator"].startswith("contrastive-") and "metric.generated/fid_ci" in champion.tags
    )
    fid, ci = float(champion.tags["metric.generated/fid"]), float(champion.tags["metric.generated/fid_ci"])
    assert f"| {fid:.4g} ± {ci:.2g} |" in champion.description
    # Few tags: the criterion's metric and interval, not every measurement (those are in the description).
    assert {k for k in champion.tags if k.startswith("metric.")} == {
        "metric.generated/fid",
        "metric.generated/fid_ci",
    }
    assert "`real/top1`" in champion.description


@pytest.mark.slow
def test_a_challenger_description_compares_with_the_champion(records):
    client = records["client"]
    champion = client.get_model_version_by_alias("mmm-text2motion", "champion")
    challenger = client.get_model_version_by_alias("mmm-text2motion", "challenger")
    assert challenger.run_id != champion.run_id and int(challenger.version) > int(champion.version)
    new, old = float(challenger.tags["metric.generated/fid"]), float(champion.tags["metric.generated/fid"])
    text = challenger.description
    assert text.startswith(f"### mmm-text2motion v{challenger.version}: `challenger`, not promoted")
    assert f"| `generated/fid` | min (lower is better) | {MARGIN:g} | {new:.4g} ± " in text
    assert (
        f"| champion (v{champion.version}) |" in text
        and f"| {old:.4g} ± " in text
        and f"| < {old - MARGIN:.4g} | not better |" in text
    )
    assert "**Verdict: challenger.** Does not beat the champion" in text
    assert f"(#/models/mmm-text2motion/versions/{champion.version}) (stays champion)" in text
    assert links_resolve(client, text) == 1 and versions_resolve(client, text) == 1
    assert challenger.tags["promotion"].startswith("challenger: does not beat the champion")
    # `mmm models list`: aliases, then the verdict and its reason, first.
    from mmm.registry.versions import list_models

    listing = list_models(client, names=("mmm-text2motion",)).splitlines()
    line = next(i for i, row in enumerate(listing) if row.strip().startswith(f"v{challenger.version} "))
    assert listing[line].split()[1:3] == ["challenger", "challenger:"] and "not better" in listing[line]
    assert listing[line + 1].strip().startswith("data ") and "generated/fid=" in listing[line + 1]


@pytest.mark.slow
def test_the_logged_bundle_knows_its_registered_versions(records):
    client = records["client"]
    for alias in ("champion", "challenger"):
        version = client.get_model_version_by_alias("mmm-text2motion", alias)
        assert version.source.startswith("models:/m-")
        model = client.get_logged_model(version.source[len("models:/") :])
        # What the dashboard's logged-model page reads ("Not registered" without it), as
        # mlflow.register_model writes it.
        assert {"name": "mmm-text2motion", "version": int(version.version)} in json.loads(
            model.tags["mlflow.modelVersions"]
        )
        assert model.source_run_id == version.run_id
        assert version.version in {
            v.version
            for v in client.search_model_versions("name='mmm-text2motion'")
            if v.source == version.source
        }
    # Logging the bundles into the stage-2 run left its duration the training's (it ended before the next
    # step did).
    stage2 = client.get_run(records["steps"]["stage2"].data.tags["output.run_id"])
    assert (
        stage2.info.status == "FINISHED" and stage2.info.end_time <= records["steps"]["stage2"].info.end_time
    )


@pytest.mark.slow
def test_tokenizer_and_evaluator_versions_are_described(records):
    client = records["client"]
    tokenizer = client.get_model_version_by_alias("mmm-tokenizer", "champion")
    assert (
        f"/registered/mmm-tokenizer-{tokenizer.tags['weights.sha256'][:12]}" in tokenizer.source
        and "Stage-1 motion tokenizer" in tokenizer.description
    )
    assert (
        "tokenizer.identity" in tokenizer.tags
        and tokenizer.tags["tokenizer.identity"] in tokenizer.description
    )
    evaluator = client.get_model_version_by_alias("mmm-evaluator", "champion")
    assert (
        "contrastive text-motion evaluator" in evaluator.description
        and "test split, by its training run" in evaluator.description
    )


@pytest.mark.slow
def test_evaluation_run_holds_its_table_and_links(records):
    client, steps = records["client"], records["steps"]
    run = client.get_run(steps["evaluate"].data.tags["output.run_id"])
    assert run.info.run_name.startswith("evaluate-synthetic-") and run.info.status == "FINISHED"
    description = run.data.tags[DESCRIPTION_TAG]
    table = (
        open(client.download_artifacts(run.info.run_id, "evaluation.md", str(records["workdir"])))
        .read()
        .strip()
    )
    assert table in description and "| Generated |" in description
    # The model's own run (stage 2) is linked and exists.
    assert (
        links_resolve(client, description) == 1 and steps["stage2"].data.tags["output.run_id"] in description
    )
    assert "generated/fid" in run.data.metrics and not any(k.endswith("_ci") for k in run.data.metrics)
    assert "± " in description  # the intervals are in the table
    commit = git_commit()
    if commit is not None:
        assert run.data.tags[GIT_COMMIT_TAG] == commit
    assert dataset_contexts(run) == {run.data.tags["data.fingerprint"]: "evaluation"}
    # The run covers the evaluation: it started before the step's work and ended with it.
    step = steps["evaluate"]
    assert step.info.start_time <= run.info.start_time < run.info.end_time <= step.info.end_time
    assert (run.info.end_time - run.info.start_time) / 1000 > 0.5 * step.data.metrics["seconds"]


@pytest.mark.slow
def test_a_failed_step_is_described_on_the_parent_and_on_its_run(tmp_path):
    """The runner alone, with steps that do nothing: the description of a pipeline that fails."""
    from mmm.pipeline.runner import Context, Step, run_steps

    uri = f"sqlite:///{tmp_path}/mlflow.db"

    def boom(ctx):
        raise RuntimeError("no | such\nthing")

    steps = [
        Step("first", lambda ctx: {}, lambda ctx: {"metrics": {"val/x": 2.0}}),
        Step("second", lambda ctx: {}, boom),
        Step("third", lambda ctx: {}, lambda ctx: {}),
    ]
    with pytest.raises(RuntimeError):
        run_steps(
            "demo",
            steps,
            Context(None, uri),
            tmp_path / "state.json",
            experiment="demo-pipeline",
            artifact_root=str(tmp_path / "art"),
            dataset=lambda ctx: ("toy", str(tmp_path), "f" * 16),
        )
    client = MlflowClient(uri)
    experiment = client.get_experiment_by_name("demo-pipeline")
    parent = client.search_runs([experiment.experiment_id], "attributes.run_name LIKE 'pipeline-demo-%'")[0]
    assert parent.info.status == "FAILED"
    text = parent.data.tags[DESCRIPTION_TAG]
    assert text.startswith("### Pipeline `demo` failed") and "1 ran, 0 skipped, 1 failed of 3 steps" in text
    assert (
        "| 03 | third | not run |" in text
        and "**Failed at 02 second**: RuntimeError: no \\| such thing" in text
    )
    assert links_resolve(client, text) == 2
    assert parent.data.metrics["first/val/x"] == 2.0 and parent.data.metrics["pipeline/steps_failed"] == 1
    assert dataset_contexts(parent) == {"f" * 16: "pipeline"}
    failed = client.search_runs([experiment.experiment_id], "attributes.run_name = '02-second'")[0]
    assert failed.info.status == "FAILED" and "failed after" in failed.data.tags[DESCRIPTION_TAG]


@pytest.mark.slow
def test_adherence_is_charted_during_training_evaluated_and_measured_for_promotion(records):
    client, steps = records["client"], records["steps"]
    # Stage 2 on labelled data: one val_adherence point per validation (PIPELINE_TINY: one).
    stage2 = steps["stage2"].data.tags["output.run_id"]
    history = client.get_metric_history(stage2, "val_adherence/ordered_rate")
    assert len(history) == len(client.get_metric_history(stage2, "val/loss")) >= 1
    assert all(0.0 <= m.value <= 1.0 for m in history)
    # `mmm evaluate`: strict and order-aware figures, per group.
    evaluate = client.get_run(steps["evaluate"].data.tags["output.run_id"]).data.metrics
    assert {"adherence/rate", "adherence/ordered_rate", "adherence/single_strict"} <= set(evaluate)
    # Promotion measured them too: the version's description lists them, so a criterion may use them.
    champion = client.get_model_version_by_alias("mmm-text2motion", "champion")
    assert "`adherence/ordered_rate`" in champion.description

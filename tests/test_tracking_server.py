"""Against a real `mlflow server` (sqlite backend, proxied artifacts, loopback port): the full
pipeline trains, evaluates and promotes over HTTP, and the server's REST API shows the runs, the
metrics, the artifacts and the champion alias; generation then loads the champion from it."""

import json

import numpy as np
import pytest

from mmm.cli import main
from tests.helpers import pipeline_args
from tests.helpers.servers import free_port, get, mlflow_command, running, server_env

API = "/api/2.0/mlflow"


def search_runs(base: str, experiment_ids: list[str], filter_string: str = "") -> list[dict]:
    from tests.helpers.servers import post

    status, body = post(
        f"{base}{API}/runs/search",
        {"experiment_ids": experiment_ids, "filter": filter_string, "max_results": 100},
    )
    assert status == 200, body
    return body.get("runs", [])


def tags(run: dict) -> dict:
    return {t["key"]: t["value"] for t in run["data"].get("tags", [])}


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_pipeline_and_promotion_over_a_tracking_server(tmp_path, monkeypatch, capsys):
    import mlflow

    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server_dir = tmp_path / "server"
    server_dir.mkdir()
    command = [
        *mlflow_command(),
        "server",
        "--backend-store-uri",
        f"sqlite:///{server_dir}/mlflow.db",
        "--artifacts-destination",
        str(server_dir / "artifacts"),
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
        "--workers",
        "1",
    ]
    client_dir = tmp_path / "client"
    client_dir.mkdir()
    monkeypatch.chdir(client_dir)
    previous = mlflow.get_tracking_uri()
    with running(command, base, tmp_path / "server.log", server_dir, server_env()):
        try:
            assert main(["pipeline", "full", *pipeline_args(client_dir, base)]) == 0
        finally:
            mlflow.set_tracking_uri(previous)
        capsys.readouterr()

        # Runs: the parent with a finished nested run per step.
        status, body = get(f"{base}{API}/experiments/get-by-name", experiment_name="mmm-pipeline")
        assert status == 200, body
        pipeline_experiment = body["experiment"]["experiment_id"]
        parents = search_runs(
            base,
            [pipeline_experiment],
            "tags.`mmm.pipeline` = 'full' and attributes.run_name LIKE 'pipeline-full-%'",
        )
        assert len(parents) == 1 and parents[0]["info"]["status"] == "FINISHED"
        children = search_runs(
            base, [pipeline_experiment], f"tags.mlflow.parentRunId = '{parents[0]['info']['run_id']}'"
        )
        by_step = {tags(c)["mmm.step"]: c for c in children}
        assert len(by_step) == 9 and all(c["info"]["status"] == "FINISHED" for c in children)

        # Metrics: the stage-1 run's training curve (4 steps, then 2 of the decoder alone) and its
        # validation MPJPE.
        stage1 = tags(by_step["stage1"])["output.run_id"]
        status, history = get(f"{base}{API}/metrics/get-history", run_id=stage1, metric_key="train/loss")
        assert (
            status == 200
            and len(history["metrics"]) == 6
            and all(np.isfinite(m["value"]) for m in history["metrics"])
        )
        status, run = get(f"{base}{API}/runs/get", run_id=stage1)
        metrics = {m["key"]: m["value"] for m in run["run"]["data"]["metrics"]}
        assert metrics["val/mpjpe_root_aligned_mm"] > 0

        # Artifacts: stored by the server (proxied), none in the client's local artifact folder.
        status, listing = get(f"{base}{API}/artifacts/list", run_id=stage1, path="checkpoints")
        assert status == 200 and {f["path"] for f in listing["files"]} >= {
            "checkpoints/best.ckpt",
            "checkpoints/last.ckpt",
        }
        assert run["run"]["info"]["artifact_uri"].startswith("mlflow-artifacts:")
        assert not (client_dir / "art").exists()
        assert list((server_dir / "artifacts").rglob("best.ckpt"))

        # The champion alias of each registered model, the text-to-motion one with its bundle.
        for name in ("mmm-evaluator", "mmm-tokenizer", "mmm-text2motion"):
            status, found = get(f"{base}{API}/registered-models/alias", name=name, alias="champion")
            assert status == 200, found
        version = found["model_version"]
        assert version["run_id"] == tags(by_step["stage2"])["output.run_id"]
        version_tags = {t["key"]: t["value"] for t in version["tags"]}
        assert (
            version_tags["promotion"] == "champion: the first version promoted (no champion yet)"
            and "metric.generated/fid" in version_tags
        )
        status, missing = get(f"{base}{API}/registered-models/alias", name="mmm-text2motion", alias="nope")
        assert status == 400 and "nope" in missing["message"], missing

        # Generation from the server's champion.
        assert (
            main(
                [
                    "generate",
                    "--text",
                    "a person walks forward",
                    "--length",
                    "40",
                    "--tracking-uri",
                    base,
                    "--out",
                    str(client_dir / "gen"),
                ]
            )
            == 0
        )
        meta = json.loads((client_dir / "gen/0/meta.json").read_text())
        assert (
            meta["model"]["reference"] == "models:/mmm-text2motion@champion"
            and meta["model"]["run_id"] == version["run_id"]
        )
        assert np.load(client_dir / "gen/0/joints.npy").shape == (40, 22, 3)

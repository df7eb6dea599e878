"""Where the embedded store keeps its artifacts."""

from pathlib import Path

import pytest

from mmm.tracking import artifact_location, prepare_experiment


@pytest.mark.parametrize(
    ("uri", "root", "expected"),
    [
        ("sqlite:////data/runs/mlflow.db", "mlartifacts", "/data/runs/mlartifacts"),
        ("sqlite:////data/runs/mlflow.db?timeout=30", "art", "/data/runs/art"),
        ("sqlite:////data/runs/mlflow.db", "/srv/artifacts", "/srv/artifacts"),
    ],
)
def test_a_relative_artifact_root_sits_beside_the_sqlite_database(uri, root, expected):
    assert artifact_location(uri, root) == Path(expected).as_uri()


def test_a_relative_database_and_root_resolve_in_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert artifact_location("sqlite:///mlflow.db", "mlartifacts") == (tmp_path / "mlartifacts").as_uri()
    assert artifact_location("sqlite:///store/mlflow.db", "art") == (tmp_path / "store" / "art").as_uri()
    assert artifact_location("sqlite:///:memory:", "art") == (tmp_path / "art").as_uri()


def test_uris_pass_through_and_a_server_keeps_its_own_store():
    assert artifact_location("sqlite:////data/mlflow.db", "s3://bucket/mmm") == "s3://bucket/mmm"
    assert artifact_location("http://127.0.0.1:5000", "mlartifacts") is None
    assert artifact_location("https://mlflow.example.org", "mlartifacts") is None


def test_a_store_in_another_folder_never_writes_into_the_working_directory(tmp_path, monkeypatch):
    from mlflow import MlflowClient

    work, store = tmp_path / "work", tmp_path / "store"
    work.mkdir()
    store.mkdir()
    monkeypatch.chdir(work)
    uri = f"sqlite:///{store}/mlflow.db"
    client = MlflowClient(uri)
    experiment_id = prepare_experiment(client, "where-test", artifact_location(uri, "mlartifacts"))
    run = client.create_run(experiment_id)
    (work / "note.txt").write_text("x")
    client.log_artifact(run.info.run_id, str(work / "note.txt"))
    client.set_terminated(run.info.run_id)
    logged = list((store / "mlartifacts").rglob("note.txt"))
    assert len(logged) == 1
    assert sorted(p.name for p in work.iterdir()) == ["note.txt"]

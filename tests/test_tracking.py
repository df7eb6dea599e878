"""Where the embedded store keeps its artifacts."""

from pathlib import Path

import pytest

from mmm.tracking import (
    StoreNotFound,
    artifact_location,
    existing_store,
    prepare_experiment,
    resolve_tracking_uri,
    store_for_reading,
)


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


def test_reading_a_store_never_creates_one_and_names_a_file_that_is_not_one(tmp_path, monkeypatch):
    from mmm.resolve import ModelNotFound, champion_reference, newest_run_checkpoint, registered_version

    monkeypatch.chdir(tmp_path)
    missing = f"sqlite:///{tmp_path}/typo/mlflow.db"
    assert existing_store(missing) is False and existing_store("http://127.0.0.1:5000") is True
    assert champion_reference(missing) is None
    assert newest_run_checkpoint(missing, "mmm-stage2", tmp_path / "cache") is None
    with pytest.raises(ModelNotFound, match="no MLflow store at"):
        registered_version("models:/mmm-text2motion@champion", missing)
    with pytest.raises(StoreNotFound, match="no MLflow store at .*typo/mlflow.db"):
        store_for_reading(missing)
    assert not (tmp_path / "typo").exists()
    # A relative store resolves in the working directory, and is not created there either.
    with pytest.raises(StoreNotFound, match=str(tmp_path / "mlflow.db")):
        store_for_reading("sqlite:///mlflow.db")
    assert list(tmp_path.iterdir()) == []

    not_a_store = tmp_path / "motion.npy"
    not_a_store.write_bytes(b"\x93NUMPY" + bytes(100))
    with pytest.raises(StoreNotFound, match="motion.npy is not an SQLite database"):
        champion_reference(f"sqlite:///{not_a_store}")
    (tmp_path / "empty.db").touch()  # an empty file is a new database to SQLite: opened as one
    assert existing_store(f"sqlite:///{tmp_path}/empty.db") is True


def test_a_database_path_is_its_sqlite_uri_and_a_file_store_is_refused_with_the_uri_to_give(
    tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    assert resolve_tracking_uri("mlflow.db") == f"sqlite:///{tmp_path}/mlflow.db"
    assert resolve_tracking_uri(f"{tmp_path}/runs/store.sqlite") == f"sqlite:///{tmp_path}/runs/store.sqlite"
    # What MLflow reads as its file store (in maintenance mode in MLflow 3): named, with the fix.
    (tmp_path / "mlruns").mkdir()
    for uri in ("mlruns", f"file://{tmp_path}/mlruns", "outputs/experiments"):
        with pytest.raises(
            ValueError, match=rf"--tracking-uri {uri}: not an MLflow store .*sqlite:///path/to/mlflow.db"
        ):
            resolve_tracking_uri(uri)
    for uri in ("http://127.0.0.1:5000", "databricks", "sqlite:////data/mlflow.db"):
        assert resolve_tracking_uri(uri) == uri

"""What every MLflow run of the package shares so the dashboard reads well: names that say what a
run is, descriptions with links, the code version, dataset inputs, and experiment descriptions.

Links are the dashboard's own hash routes (`#/experiments/<id>/runs/<id>`, `#/models/<name>/versions/<n>`),
relative, so they work whatever host and port serve the store.
"""

from __future__ import annotations

import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from mmm.kinds import KINDS

DESCRIPTION_TAG = "mlflow.note.content"  # the run's / experiment's / version's markdown description in the UI
GIT_COMMIT_TAG = "mlflow.source.git.commit"
# Experiments of a training package: the dashboard opens them in its classic (machine learning) view.
EXPERIMENT_KIND_TAG, EXPERIMENT_KIND = "mlflow.experimentKind", "custom_model_development"
TRAINING_VIEW = "?workflowType=machine_learning"  # without it MLflow 3.17 may open a page in its GenAI view

EXPERIMENT_DESCRIPTIONS = {
    **{kind.experiment: kind.description for kind in KINDS.values()},
    "mmm-evaluation": (
        "`mmm evaluate` runs: the replicated protocol, reconstruction and prompt adherence; each run's "
        "description holds its table."
    ),
    "mmm-pipeline": (
        "`mmm pipeline` runs: one parent run per pipeline (its description: the steps in order, with "
        "links), one nested run per step."
    ),
    "mmm-ablations": (
        "`mmm ablate` sweeps (the supplementary's Tables 8-13): a parent run per sweep, one nested run "
        "per setting."
    ),
    "mmm-import": "The authors' released checkpoints imported with `mmm import released`.",
}


@dataclass
class TrackingConfig:
    """MLflow: an embedded sqlite store by default; a team points tracking_uri at its server."""

    enabled: bool = True
    tracking_uri: str = "sqlite:///mlflow.db"
    artifact_root: str = "mlartifacts"  # new experiments on a sqlite store; relative: beside the database
    experiment: str = "mmm"
    run_name: str | None = None
    log_checkpoints: bool = True


SQLITE = "sqlite:///"
BARE_SCHEMES = ("databricks", "databricks-uc", "uc")  # MLflow URIs with no "://"


def sqlite_database(uri: str) -> str | None:
    """The database file of a sqlite:/// URI as written (relative or absolute, without its query
    string), None for any other store."""
    return uri[len(SQLITE) :].split("?", 1)[0] if uri.startswith(SQLITE) else None


def resolve_tracking_uri(uri: str) -> str:
    """Make a relative sqlite path absolute, so every process and the dashboard agree on it. A
    plain path to a database file (`mlflow.db`, `/path/to/mlflow.db`) is read as its sqlite:///
    URI; a folder or file:// store (MLflow's file store, in maintenance mode in MLflow 3) is
    refused with the URI to give instead."""
    if uri.startswith(SQLITE):
        if not uri[len(SQLITE) :].startswith("/"):
            return SQLITE + str(Path(uri[len(SQLITE) :]).resolve())
        return uri
    if uri.startswith("file:") or (uri and "://" not in uri and ":" not in uri and uri not in BARE_SCHEMES):
        path = Path(uri.removeprefix("file://").removeprefix("file:")).expanduser()
        if uri.startswith("file:") or path.is_dir() or path.suffix not in (".db", ".sqlite", ".sqlite3"):
            raise ValueError(
                f"--tracking-uri {uri}: not an MLflow store this package uses (a folder or file:// store is "
                "MLflow's file store, which MLflow 3 no longer develops); give the store's database as "
                "sqlite:///path/to/mlflow.db (or a path ending in .db), or a tracking server's http:// "
                "address"
            )
        return SQLITE + str(path.resolve())
    return uri


SQLITE_HEADER = b"SQLite format 3\x00"


class StoreNotFound(FileNotFoundError):
    """A store a command only reads from that is not there, or not an MLflow database."""


def existing_store(uri: str) -> bool:
    """Whether a command that only reads may open `uri`: False for a sqlite store whose database
    file does not exist (opening it would create an empty one, e.g. at a mistyped path); a file
    that is not an SQLite database is a StoreNotFound naming it. Other stores (servers): True."""
    database = sqlite_database(uri)
    if database in (None, "", ":memory:"):
        return True
    path = Path(database)
    if not path.is_file():
        return False
    with open(path, "rb") as fh:
        header = fh.read(len(SQLITE_HEADER))
    if header and header != SQLITE_HEADER:  # an empty file is a new database to SQLite
        raise StoreNotFound(
            f"--tracking-uri {uri}: {path} is not an SQLite database; give the mlflow.db of a store "
            "(sqlite:///path/to/mlflow.db) or a tracking server's http:// address"
        )
    return True


def store_for_reading(uri: str) -> str:
    """`uri` resolved, for a command that only reads the store; StoreNotFound when it is not there."""
    uri = resolve_tracking_uri(uri)
    if not existing_store(uri):
        raise StoreNotFound(
            f"--tracking-uri {uri}: no MLflow store at {sqlite_database(uri)} (nothing trained, imported or "
            "promoted there yet); run the command where the store is or give its path"
        )
    return uri


def artifact_location(tracking_uri: str, artifact_root: str) -> str | None:
    """Where a new experiment keeps its artifacts: artifact_root as given when it is a URI
    (s3://...), None against a tracking server (the server's own store, which it serves to every
    client), else a local folder. A relative folder sits beside a sqlite store's database file, so
    the store is one self-contained folder wherever the command runs (and a store in a temporary
    folder never writes into the working directory)."""
    if "://" in artifact_root or artifact_root.startswith("mlflow-artifacts:"):
        return artifact_root
    if tracking_uri.split(":", 1)[0] in ("http", "https", "databricks"):
        return None
    root = Path(artifact_root)
    database = sqlite_database(tracking_uri)
    if not root.is_absolute() and database not in (None, "", ":memory:"):
        root = Path(database).parent / root
    return root.resolve().as_uri()


def run_link(experiment_id: str, run_id: str, text: str | None = None) -> str:
    return f"[{text or run_id[:8]}](#/experiments/{experiment_id}/runs/{run_id}{TRAINING_VIEW})"


def version_link(name: str, version: str | int, text: str | None = None) -> str:
    return f"[{text or f'{name} v{version}'}](#/models/{name}/versions/{version})"


def experiment_url(base: str, experiment_id: str) -> str:
    """The experiment's page in the classic training view (MLflow 3 opens new stores in its GenAI view)."""
    return f"{base.rstrip('/')}/#/experiments/{experiment_id}/runs{TRAINING_VIEW}"


def source_tags(command: str) -> dict[str, str]:
    """What the run page's "Source" shows: the command that made the run, and the git commit."""
    commit = git_commit()
    return {
        "mlflow.source.name": command,
        "mlflow.source.type": "LOCAL",
        **({GIT_COMMIT_TAG: commit} if commit else {}),
    }


def timestamp() -> str:
    return time.strftime("%Y%m%d-%H%M%S")


def git_commit(root: Path | None = None) -> str | None:
    """The commit of this package's source checkout at `root` (default: the one this module is in),
    None outside one (an installed package, whose parents may be some other repository)."""
    root = Path(__file__).resolve().parents[2] if root is None else root
    if not ((root / "pyproject.toml").is_file() and (root / "src" / "mmm" / "__init__.py").is_file()):
        return None
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def prepare_experiment(client, name: str, artifact_location: str | None = None) -> str:
    """The id of experiment `name`, created when missing (another process creating it at the same
    time is not an error), with its description and the classic-view kind set once."""
    # MLflow is imported by the functions that talk to a store: configs read TrackingConfig from here
    from mlflow.exceptions import MlflowException

    found = client.get_experiment_by_name(name)
    if found is None:
        try:
            experiment_id = client.create_experiment(name, artifact_location=artifact_location)
        except MlflowException:
            found = client.get_experiment_by_name(name)
            if found is None:
                raise
            experiment_id = found.experiment_id
    else:
        experiment_id = found.experiment_id
    tags = found.tags if found is not None else {}
    if tags.get(EXPERIMENT_KIND_TAG) != EXPERIMENT_KIND:
        client.set_experiment_tag(experiment_id, EXPERIMENT_KIND_TAG, EXPERIMENT_KIND)
    if DESCRIPTION_TAG not in tags and name in EXPERIMENT_DESCRIPTIONS:
        client.set_experiment_tag(experiment_id, DESCRIPTION_TAG, EXPERIMENT_DESCRIPTIONS[name])
    return experiment_id


def log_dataset_input(
    client, run_id: str, name: str, root: str | Path, fingerprint: str, context: str = "training"
) -> None:
    """Record the dataset a run read as its MLflow dataset input (name, digest = content
    fingerprint, source = the folder)."""
    from mlflow.entities import Dataset, DatasetInput, InputTag  # see prepare_experiment

    dataset = Dataset(
        name=name,
        digest=fingerprint,
        source_type="local",
        source=str(Path(root).resolve()),
        schema=None,
        profile=None,
    )
    client.log_inputs(
        run_id, datasets=[DatasetInput(dataset, tags=[InputTag("mlflow.data.context", context)])]
    )


def dashboard_links(client, base_url: str) -> list[str]:
    """Where to look, as absolute dashboard URLs: each of the package's experiments in the classic
    view (with its newest run), and the registered models."""
    lines = []
    for experiment in client.search_experiments(order_by=["name ASC"]):
        if not experiment.name.startswith("mmm"):
            continue
        recent = client.search_runs(
            [experiment.experiment_id], order_by=["attributes.start_time DESC"], max_results=50
        )
        # A pipeline's steps start after it: the newest top-level run is the one to open.
        newest = [r for r in recent if "mlflow.parentRunId" not in r.data.tags] or recent
        line = f"{experiment.name:18s} {experiment_url(base_url, experiment.experiment_id)}"
        if newest:
            run = newest[0].info
            line += (
                f"\n{'':18s} newest run {run.run_name}: "
                f"{base_url.rstrip('/')}/#/experiments/{experiment.experiment_id}/runs/{run.run_id}{TRAINING_VIEW}"
            )
        lines.append(line)
    lines.append(f"{'registered models':18s} {base_url.rstrip('/')}/#/models")
    return lines

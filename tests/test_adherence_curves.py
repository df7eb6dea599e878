"""benchmarks/adherence_curves.py: the README's learning-curve plots, read back from MLflow."""

import subprocess
import sys
from pathlib import Path

import numpy as np
from mlflow.tracking import MlflowClient
from PIL import Image

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "adherence_curves.py"


def _plot(tmp_path, *args):
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args, "--tracking-uri", f"sqlite:///{tmp_path}/mlflow.db"],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_plots_each_runs_curves_and_refuses_a_run_without_them(tmp_path):
    # The client, not mlflow's module-level API: its active experiment would leak into later tests.
    client = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    experiment = client.create_experiment("curves")
    curved, flat = (client.create_run(experiment).info for _ in range(2))
    for step, value in [(100, 0.2), (200, 0.5), (300, 0.7)]:
        client.log_metric(curved.run_id, "val_adherence/ordered_rate", value, step=step)
        client.log_metric(curved.run_id, "val_adherence/single_ordered", value + 0.1, step=step)
        client.log_metric(curved.run_id, "val_adherence/counts_ordered", value - 0.1, step=step)
    client.log_metric(flat.run_id, "val/loss", 1.0)
    out = tmp_path / "curves.png"

    done = _plot(tmp_path, f"{curved.run_id}=demo", "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert "demo" in done.stdout
    rgb = np.asarray(Image.open(out).convert("RGB")).astype(int)
    coloured = (rgb.max(axis=2) - rgb.min(axis=2)) > 80  # the curves; axes and text are grey
    assert rgb.shape[1] > 400 and coloured.sum() > 300

    refused = _plot(tmp_path, flat.run_id, "--out", str(tmp_path / "none.png"))
    assert refused.returncode != 0
    assert flat.run_id in refused.stderr and "adherence_captions" in refused.stderr
    assert not (tmp_path / "none.png").exists()
    missing = _plot(tmp_path, "0" * 32, "--out", str(tmp_path / "none.png"))
    assert missing.returncode != 0 and "--tracking-uri" in missing.stderr

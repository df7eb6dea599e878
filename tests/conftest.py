import os
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
_ref = REPO.parent / "shared" / "reference"
REFERENCE = _ref if _ref.is_dir() else None

# Tests read configs from the checkout and never touch a user's MLflow store.
os.environ.setdefault("MMM_CONF_DIR", str(REPO / "conf"))


@pytest.fixture(scope="session", autouse=True)
def working_directory_outside_the_checkout(tmp_path_factory):
    """The whole session runs in a folder of its own. The package's relative defaults would
    otherwise write into the checkout: sqlite:///mlflow.db, outputs/, the download caches
    (outputs/cache/models, outputs/cache/bundles). Tests that need a folder of their own still
    change into it."""
    checkout = os.getcwd()
    os.chdir(tmp_path_factory.mktemp("cwd"))
    yield
    os.chdir(checkout)


@pytest.fixture
def reference_dir():
    if REFERENCE is None:
        pytest.skip("../shared/reference not available")
    return REFERENCE


@pytest.fixture(scope="session")
def walker_dataset(tmp_path_factory):
    from tests.helpers import write_walker_dataset

    return write_walker_dataset(tmp_path_factory.mktemp("walkers") / "ds")


@pytest.fixture(scope="session")
def trained(walker_dataset, tmp_path_factory):
    """Tiny stage-1 and stage-2 models trained for a few steps on the walker dataset (shared)."""
    from mmm.training.configs import load_stage2_config
    from mmm.training.stage2 import train_stage2
    from tests.helpers import stage2_overrides, train_tiny_stage1

    out = tmp_path_factory.mktemp("trained")
    train_tiny_stage1(walker_dataset, out)
    result = train_stage2(
        load_stage2_config(
            stage2_overrides(walker_dataset, out, **{"trainer.max_steps": 4, "trainer.val_check_interval": 4})
        )
    )
    return {
        "out": out,
        "checkpoint": result.best_checkpoint,
        "uri": f"sqlite:///{out}/mlflow.db",
        "walker": walker_dataset,
    }


@pytest.fixture(scope="session")
def parts_trained(walker_dataset, tmp_path_factory):
    """A tiny part-aware tokenizer and transformer trained for a few steps on the walker dataset
    (shared; tests may register and alias its runs in its store, never retrain them)."""
    from mmm.training.configs import load_stage2_config
    from mmm.training.stage2 import train_stage2
    from tests.helpers import stage2_overrides, train_tiny_stage1

    out = tmp_path_factory.mktemp("parts")
    stage1 = train_tiny_stage1(
        walker_dataset, out, "model.tokenizer.part_aware=true", "logger.experiment=mmm-stage1-parts"
    )
    # The stage-1 model given as its run (recorded so; loading resolves it in the store, not by a path
    # outside outputs/).
    overrides = stage2_overrides(
        walker_dataset,
        out,
        **{
            "stage1": f"runs:/{stage1.run_id}",
            "trainer.max_steps": 4,
            "trainer.val_check_interval": 4,
            "output_dir": f"{out}/s2p",
        },
    )
    result = train_stage2(load_stage2_config(overrides, parts=True))
    return {
        "out": out,
        "stage1": stage1,
        "stage2": result,
        "uri": f"sqlite:///{out}/mlflow.db",
        "walker": walker_dataset,
    }

import os
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
_ref = REPO.parent / "shared" / "reference"
REFERENCE = _ref if _ref.is_dir() else None

# Tests read configs from the checkout and never touch a user's MLflow store.
os.environ.setdefault("MMM_CONF_DIR", str(REPO / "conf"))
sys.path.insert(0, str(TESTS))


@pytest.fixture
def reference_dir():
    if REFERENCE is None:
        pytest.skip("../shared/reference not available")
    return REFERENCE


@pytest.fixture(scope="session")
def walker_dataset(tmp_path_factory):
    from helpers import write_walker_dataset

    return write_walker_dataset(tmp_path_factory.mktemp("walkers") / "ds")

"""The text-motion evaluator and the length estimator under DDP (2 CPU processes over gloo): the
ranks train on different batches, end with the same weights, and hold the whole validation set's
metrics, so both choose the same best checkpoint."""

import pytest
import torch

from tests.helpers import run_ddp_worker


@pytest.mark.slow
@pytest.mark.ddp
@pytest.mark.parametrize("kind", ["evaluator", "length"])
def test_ddp_ranks_agree_and_validate_on_the_whole_set(tmp_path, kind):
    r0, r1 = run_ddp_worker("evaluator_length_ddp.py", tmp_path, kind, out_dir=tmp_path)
    assert not torch.equal(r0["first_batch"], r1["first_batch"])  # each rank its own shard
    assert torch.equal(r0["weights"], r1["weights"])
    assert r0["step"] == r1["step"] == 12
    assert r0["metrics"] == r1["metrics"] and "val/loss" in r0["metrics"]
    # Each rank validated 8 of the 16 items; the loss both hold is the mean over all 16.
    assert r0["shard_count"] == r1["shard_count"] == 8
    own = [r["shard_sum"] / r["shard_count"] for r in (r0, r1)]
    assert abs(own[0] - own[1]) > 1e-4  # the halves differ, so a rank's own mean would show
    whole = (r0["shard_sum"] + r1["shard_sum"]) / 16
    assert r0["metrics"]["val/loss"] == pytest.approx(whole, rel=1e-5)

"""Several nodes started for real: `trainer=multinode` as 2 nodes x 1 process, each node its own
torchrun, meeting through the c10d rendezvous on 127.0.0.1 (gloo on the CPU).

Checked per stage: identical weights and codebooks on both ranks, one MLflow run, checkpoints
written by rank 0 only, data shards disjoint and complete. And resuming across process counts:
the same global batch (4 per process on 2, or 8 on 1) continues exactly where it stopped, in both
directions; another global batch is refused.
"""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from mlflow.tracking import MlflowClient

from tests.helpers import stage2_overrides, tiny_stage1_config, tiny_stage1_overrides
from tests.helpers.servers import free_port, stop

pytestmark = [pytest.mark.slow, pytest.mark.ddp]

WORKER = Path(__file__).parent / "ddp_workers" / "multinode_worker.py"
LAUNCH_TIMEOUT_S = 420  # a two-node leg takes about 20 s on 2 cores
TWO_NODES = [
    "trainer=multinode",
    "trainer.num_nodes=2",
    "trainer.devices=1",
    "trainer.accelerator=cpu",
    "trainer.process_group_backend=gloo",
    "trainer.enable_progress_bar=false",
]


def launch_two_nodes(probe: Path, args: list[str], run_id: str, resume: str | None = None) -> None:
    """`torchrun --nnodes=2 --nproc-per-node=1` twice, as two machines would start it."""
    probe.mkdir(parents=True)
    port = free_port()
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nnodes=2",
        "--nproc-per-node=1",
        "--rdzv-backend=c10d",
        f"--rdzv-endpoint=127.0.0.1:{port}",
        f"--rdzv-id={run_id}",
        "--max-restarts=0",
        # Its logs beside the probe: by default each torchrun leaves a torchelastic_* folder in /tmp.
        f"--log-dir={probe.parent / (probe.name + '-torchrun')}",
        str(WORKER),
        str(probe),
        *args,
        *TWO_NODES,
        *(["--resume", resume] if resume else []),
    ]
    root = str(Path(__file__).parent.parent)
    # One core per "node", as on two machines: two processes with a thread per core each would
    # oversubscribe the cores, and OpenMP threads waiting on a busy core made stage 2's tokenizing
    # (the code search) 20 times slower here, 7 minutes instead of 20 seconds.
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]),
        "OMP_NUM_THREADS": "1",
    }
    nodes = [
        subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
            start_new_session=True,  # a process group: `stop` ends the torchrun and its worker
        )
        for _ in range(2)
    ]
    deadline = time.monotonic() + LAUNCH_TIMEOUT_S
    logs = ["", ""]
    try:
        for i, node in enumerate(nodes):
            logs[i] = node.communicate(timeout=max(1.0, deadline - time.monotonic()))[0]
    except subprocess.TimeoutExpired:
        # Stop both torchruns and their workers, or they would go on taking the cores from the
        # tests after this one.
        for node in nodes:
            stop(node)
        logs = [log or node.communicate()[0] or "" for node, log in zip(nodes, logs)]
        pytest.fail(
            f"two-node launch still running after {LAUNCH_TIMEOUT_S} s:\n"
            + "\n".join(log[-3000:] for log in logs)
        )
    for node, log in zip(nodes, logs):
        assert node.returncode == 0, log[-4000:]


def check_ranks(probe: Path) -> tuple[dict, dict]:
    """The two ranks' probes, after checking what every multi-node run must hold."""
    r0, r1 = (torch.load(probe / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    assert r0["state"].keys() == r1["state"].keys()
    for key in r0["state"]:  # weights and buffers: the codebook, its EMA statistics
        assert torch.equal(r0["state"][key], r1["state"][key]), key
    assert r0["global_step"] == r1["global_step"]
    # Shards: every index of the epoch once, on one rank (the last rank may repeat one as padding).
    shard0, shard1 = r0["first_epoch"], r1["first_epoch"]
    n = max(shard0 + shard1) + 1
    assert len(shard0) == len(shard1) == -(-n // 2)
    assert set(shard0) | set(shard1) == set(range(n))
    assert len(set(shard0) & set(shard1)) == 2 * len(shard0) - n <= 1
    writes = (probe / "checkpoint-writes.txt").read_text().splitlines()
    assert writes and all(line.startswith("0 ") for line in writes), writes
    return r0, r1


def weights(checkpoint: Path) -> dict:
    return torch.load(checkpoint, map_location="cpu", weights_only=True)["state_dict"]


def test_stage1_and_stage2_on_two_nodes_and_resumed_across_process_counts(walker_dataset, tmp_path):
    from mmm.training.stage1 import train_stage1

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    # No codebook resets: they draw random codes, and a reset drawn on 2 processes is another draw
    # than on 1; everything else a step does is a function of its samples.
    # No decoder refinement either: it would follow each leg's max_steps (6, 12, 18), not only the last.
    # In float32: a bfloat16 step rounds one batch of 8 and two of 4 differently, past the tolerance.
    stage1 = [
        "callbacks.reset_every_n_steps=100000",
        "trainer.val_check_interval=6",
        "refine.steps=0",
        "trainer.precision=32-true",
    ]

    def one_process(steps: int, *extra: str, resume=None):
        cfg = tiny_stage1_config(walker_dataset, tmp_path, *stage1, f"trainer.max_steps={steps}", *extra)
        return train_stage1(cfg, resume=resume)

    # 6 steps on 1 process (batch 8), 6 more on 2 nodes (4 each), 6 more on 1 process again...
    first = one_process(6)
    run_dir = Path(first.last_checkpoint).parent.parent
    launch_two_nodes(
        tmp_path / "probe1",
        [
            "stage1",
            *tiny_stage1_overrides(
                walker_dataset, tmp_path, *stage1, "data.batch_size=4", "trainer.max_steps=12"
            ),
        ],
        "mmm-stage1",
        resume=first.last_checkpoint,
    )
    check_ranks(tmp_path / "probe1")
    last = run_dir / "checkpoints" / "last.ckpt"
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == 12
    with pytest.raises(ValueError, match=r"changed global batch \(batch_size 4 in the checkpoint, 2 now"):
        one_process(18, "data.batch_size=2", resume=str(last))
    resumed = one_process(18, resume=str(last))
    # ... equals 18 steps on 1 process without a stop.
    straight = one_process(18, f"output_dir={tmp_path}/straight")
    a, b = weights(Path(resumed.last_checkpoint)), weights(Path(straight.last_checkpoint))
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-4, atol=1e-5, msg=key)
    runs = MlflowClient(uri).search_runs(
        [MlflowClient(uri).get_experiment_by_name("mmm-stage1").experiment_id]
    )
    assert sorted(r.info.run_id for r in runs) == sorted({first.run_id, straight.run_id})
    assert resumed.run_id == first.run_id  # the 2-node leg logged into the same run

    # Stage 2 on 2 nodes, from scratch, on that tokenizer.
    launch_two_nodes(
        tmp_path / "probe2",
        [
            "stage2",
            *stage2_overrides(
                walker_dataset,
                tmp_path,
                **{
                    "stage1": straight.best_checkpoint,
                    "data.batch_size": 4,
                    "trainer.max_steps": 4,
                    "trainer.val_check_interval": 4,
                    "callbacks.preview_captions": 0,
                    "callbacks.adherence_captions": 0,
                },
            ),
        ],
        "mmm-stage2",
    )
    r0, _ = check_ranks(tmp_path / "probe2")
    assert r0["global_step"] == 4
    stage2_runs = MlflowClient(uri).search_runs(
        [MlflowClient(uri).get_experiment_by_name("mmm-stage2").experiment_id]
    )
    assert len(stage2_runs) == 1 and stage2_runs[0].info.status == "FINISHED"
    folders = [p.name for p in (tmp_path / "s2").iterdir()]
    assert len(folders) == 1 and folders[0].startswith("job-mmm-stage2-"), folders  # one folder per launch

"""Small motions and datasets the tests build on disk."""

import math

import numpy as np
import torch

from mmm.motion.features import reference_std
from mmm.motion.quaternion import quat_about_y, quat_from_axis_angle
from mmm.motion.skeleton import T2M_SKELETON, forward_kinematics

D = 263


def make_features(T, seed):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(T, D)).astype(np.float32) * 0.1 + seed


def write_dataset(root, clips, splits, stats=True):
    """clips: id -> (T or features array, [caption lines]); splits: name -> ids."""
    (root / "new_joint_vecs").mkdir(parents=True)
    (root / "texts").mkdir()
    arrays = {}
    for i, (motion_id, (motion, lines)) in enumerate(clips.items()):
        arr = make_features(motion, i) if isinstance(motion, int) else motion
        arrays[motion_id] = arr
        np.save(root / "new_joint_vecs" / f"{motion_id}.npy", arr)
        (root / "texts" / f"{motion_id}.txt").write_text("\n".join(lines) + "\n")
    for name, ids in splits.items():
        (root / f"{name}.txt").write_text("\n".join(ids) + "\n")
    if stats:
        mean, std = reference_std(np.concatenate(list(arrays.values())), 22)
        np.save(root / "Mean.npy", mean.astype(np.float32))
        np.save(root / "Std.npy", std.astype(np.float32))
    return arrays


def turning_walker(frames=160, turns=1.25):
    """A rigid T-pose body moving on a circle and turning `turns` full turns: crosses 180 degrees."""
    t = torch.arange(frames, dtype=torch.float64)
    heading = 2 * math.pi * turns * t / frames
    root = torch.stack(
        (torch.sin(heading) * 1.5, 0.95 + 0.03 * torch.sin(t / 3), 1.5 - torch.cos(heading) * 1.5), dim=-1
    )
    quats = torch.zeros(frames, 22, 4, dtype=torch.float64)
    quats[..., 0] = 1.0
    quats[:, 0] = quat_about_y(heading)
    # Swing the arms and legs so rotations and velocities are not trivial.
    swing = quat_from_axis_angle(
        torch.tensor([1.0, 0, 0], dtype=torch.float64).expand(frames, 3), 0.5 * torch.sin(t / 4)
    )
    for j in (1, 17):
        quats[:, j] = swing
    for j in (2, 16):
        quats[:, j] = swing * torch.tensor([1.0, -1, -1, -1], dtype=torch.float64)
    return forward_kinematics(quats, root, T2M_SKELETON, chains_from_root=False)


def write_walker_dataset(root, num_clips: int = 30):
    """A small dataset of turning, arm-swinging bodies in the HumanML3D layout (80/10/10 split)."""
    from mmm.motion.features import joints_to_features

    clips = {}
    for i in range(num_clips):
        joints = turning_walker(frames=90 + 3 * i, turns=0.1 + 0.04 * i).numpy()
        clips[f"{i:06d}"] = (
            joints_to_features(joints).astype(np.float32),
            ["a person turns#a/DET person/NOUN turn/VERB#0.0#0.0"],
        )
    ids = list(clips)
    n_train, n_val = int(num_clips * 0.8), int(num_clips * 0.1)
    write_dataset(
        root,
        clips,
        {"train": ids[:n_train], "val": ids[n_train : n_train + n_val], "test": ids[n_train + n_val :]},
    )
    return root


def tiny_stage1_overrides(root, out, *extra) -> list[str]:
    """The overrides of a 4-step stage-1 run on `root` (MLflow store and outputs under `out`);
    `extra` overrides come last and win."""
    return [
        f"data.root={root}",
        "data.synthesize=null",
        "data.batch_size=8",
        "model.tokenizer.width=16",
        "model.tokenizer.num_codes=32",
        "trainer.max_steps=4",
        "refine.steps=2",
        "trainer.val_check_interval=4",
        "trainer.enable_progress_bar=false",
        "callbacks.preview_clips=0",
        "callbacks.usage_plot=false",
        f"output_dir={out}/s1",
        f"logger.tracking_uri=sqlite:///{out}/mlflow.db",
        f"logger.artifact_root={out}/art",
        *extra,
    ]


def tiny_stage1_config(root, out, *extra):
    """The config of tiny_stage1_overrides."""
    from mmm.training.configs import load_stage1_config

    return load_stage1_config(tiny_stage1_overrides(root, out, *extra))


def train_tiny_stage1(root, out, *extra):
    """A 4-step stage-1 run (tiny_stage1_config)."""
    from mmm.training.stage1 import train_stage1

    return train_stage1(tiny_stage1_config(root, out, *extra))


def train_tiny_evaluator(root, out, tracking_uri: str, output_dir: str = "ev"):
    """A contrastive evaluator of a few steps on the dataset at `root` (its TrainResult), runs in
    `tracking_uri`, files under `out`/`output_dir`."""
    from mmm.training.configs import load_evaluator_config
    from mmm.training.evaluator import train_evaluator

    overrides = {
        "data.root": root,
        "data.synthesize": "null",
        "data.batch_size": 8,
        "model.hidden_dim": 16,
        "model.embed_dim": 32,
        "model.text_hidden_dim": 32,
        "trainer.max_steps": 4,
        "trainer.val_check_interval": 4,
        "trainer.enable_progress_bar": "false",
        "output_dir": f"{out}/{output_dir}",
        "text.cache_dir": f"{out}/text",
        "logger.tracking_uri": tracking_uri,
        "logger.artifact_root": f"{out}/art",
    }
    return train_evaluator(load_evaluator_config([f"{k}={v}" for k, v in overrides.items()]))


def stage2_overrides(root, out, **extra):
    """Overrides for a tiny, short stage-2 run on `root` with everything written under `out`."""
    items = {
        "data.root": root,
        "data.synthesize": "null",
        "data.batch_size": 8,
        "model.transformer.embed_dim": 32,
        "model.transformer.num_heads": 2,
        "model.transformer.num_layers": 2,
        "trainer.max_steps": 6,
        "trainer.log_every_n_steps": 1,
        "trainer.val_check_interval": 3,
        "trainer.enable_progress_bar": "false",
        "output_dir": f"{out}/s2",
        "stage1_output_dir": f"{out}/s1",
        "token_cache_dir": f"{out}/tokens",
        "text.cache_dir": f"{out}/text",
        "logger.tracking_uri": f"sqlite:///{out}/mlflow.db",
        "logger.artifact_root": f"{out}/art",
    }
    items.update(extra)
    return [f"{k}={v}" for k, v in items.items()]


# Step overrides that make `mmm pipeline full` take seconds (tiny networks, a few steps each).
PIPELINE_TINY = {
    "evaluator": [
        "model.hidden_dim=16",
        "model.embed_dim=32",
        "model.text_hidden_dim=32",
        "trainer.max_steps=4",
        "trainer.val_check_interval=4",
        "retrieval.batch_size=8",
    ],
    "stage1": [
        "model.tokenizer.width=16",
        "model.tokenizer.num_codes=32",
        "trainer.max_steps=4",
        "refine.steps=2",
        "trainer.val_check_interval=4",
        "trainer.log_every_n_steps=1",
        "callbacks.preview_clips=0",
        "callbacks.usage_plot=false",
    ],
    "stage2": [
        "model.transformer.embed_dim=32",
        "model.transformer.num_heads=2",
        "model.transformer.num_layers=2",
        "trainer.max_steps=4",
        "trainer.val_check_interval=4",
        "callbacks.preview_captions=0",
    ],
    "length": ["model.hidden_dim=16", "trainer.max_steps=4", "trainer.val_check_interval=4"],
    "evaluate": [
        "protocol.batch_size=8",
        "protocol.replications=2",
        "protocol.mm_texts=2",
        "protocol.mm_generations=3",
        "protocol.mm_times=2",
        "protocol.diversity_times=10",
        "protocol.max_batches=null",
    ],
    "promote": [
        "protocol.batch_size=8",
        "protocol.replications=2",
        "protocol.mm_texts=2",
        "protocol.mm_generations=3",
        "protocol.mm_times=2",
        "protocol.diversity_times=10",
        "protocol.max_batches=null",
    ],
}


def pipeline_args(workdir, tracking_uri: str) -> list[str]:
    """`mmm pipeline` overrides: a 60-clip synthetic dataset, the store, state and artifacts under
    `workdir`."""
    return [
        f"data.root={workdir}/data",
        "data.synthesize.num_clips=60",
        "data.batch_size=8",
        f"logger.tracking_uri={tracking_uri}",
        f"logger.artifact_root={workdir}/art",
        f"state_file={workdir}/state.json",
        *[f"overrides.{step}=[{','.join(items)}]" for step, items in PIPELINE_TINY.items()],
    ]


def steps_of(client, parent):
    """The parent's nested runs by step (their names are `01-<step>`, `02-<step>`, ...)."""
    children = client.search_runs(
        [parent.info.experiment_id], f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
    )
    assert all(
        r.info.run_name == f"{int(r.data.tags['mmm.step.order']):02d}-{r.data.tags['mmm.step']}"
        for r in children
    )
    return {r.data.tags["mmm.step"]: r for r in children}


def newest_parent(client):
    """The newest run of `mmm pipeline full` in the store of `client`."""
    experiment = client.get_experiment_by_name("mmm-pipeline")
    return client.search_runs(
        [experiment.experiment_id],
        "tags.`mmm.pipeline` = 'full' and attributes.run_name LIKE 'pipeline-%'",
        order_by=["attributes.start_time DESC"],
    )[0]


def run_ddp_worker(
    script: str, *args, out_dir, timeout: int = 180, launch: str = "forked"
) -> tuple[dict, dict]:
    """Run tests/ddp_workers/<script> with `args` (2 processes over gloo), check that it succeeded,
    and return the states its ranks saved as <out_dir>/rank0.pt and rank1.pt.

    launch="forked": both ranks of a script whose Trainer runs on 2 devices are started here, forked
    from the preloaded server of tests/helpers/forked.py, with the environment Lightning's launcher
    would give them (8 s less per run). "subprocess": `python SCRIPT ARGS`, which starts its other
    process itself, through Lightning's own launcher or torch.multiprocessing."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from tests.helpers.forked import run_script_as_ranks

    worker = Path(__file__).resolve().parents[1] / "ddp_workers" / script
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    if launch not in ("forked", "subprocess"):
        raise ValueError(f"launch={launch!r}: 'forked' or 'subprocess'")
    if launch == "forked":
        ranks = run_script_as_ranks(worker, [str(a) for a in args], env, ranks=2, timeout=timeout)
        assert all(code == 0 for code, _ in ranks), "\n".join(
            f"rank {r}: exit {code}\n{err[-3000:]}" for r, (code, err) in enumerate(ranks)
        )
    else:
        result = subprocess.run(
            [sys.executable, str(worker), *map(str, args)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
        )
        assert result.returncode == 0, result.stderr[-3000:]
    return tuple(torch.load(Path(out_dir) / f"rank{r}.pt", weights_only=True) for r in (0, 1))

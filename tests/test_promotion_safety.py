"""Promotion, resume and concurrency safety (issue 13, items 7-12): resumes write only into the
stage's run folders and refuse what would silently change the run, registered versions point at
immutable, fingerprinted weights, promotions compare like with like and never leave the worse of
two concurrent candidates champion, and pipeline keys notice every change that matters."""

import hashlib
import logging
import multiprocessing
import os
import shutil
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from mmm.config import ConfigError
from mmm.registry.configs import Criterion
from mmm.registry.versions import promote_version, register_version, version_tags
from tests.helpers import stage2_overrides, tiny_stage1_config, train_tiny_stage1


def sha256(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def stage1_config(root, out, *extra):
    """The overrides of helpers.train_tiny_stage1 (same store and output folder under `out`), plus `extra`."""
    return tiny_stage1_config(root, out, *extra)


@pytest.fixture(scope="module")
def stage1_run(walker_dataset, tmp_path_factory):
    """A 4-step stage-1 run with its own store (tests here register and resume it)."""
    out = tmp_path_factory.mktemp("stage1-run")
    return {"out": out, "result": train_tiny_stage1(walker_dataset, out), "uri": f"sqlite:///{out}/mlflow.db"}


# -- items 7, 8: resume never writes beside a foreign checkpoint; registered weights are immutable
# ---------------
@pytest.mark.slow
def test_registered_weights_survive_a_resume_that_started_from_a_checkpoint_elsewhere(
    stage1_run, walker_dataset, tmp_path, monkeypatch
):
    from mmm.registry.configs import load_promote_config
    from mmm.registry.promote import promote
    from mmm.resolve import resolve_checkpoint
    from mmm.training.stage1 import train_stage1

    monkeypatch.chdir(tmp_path)  # the download cache (outputs/cache/models) lands here
    out, first, uri = stage1_run["out"], stage1_run["result"], stage1_run["uri"]
    overrides = [
        f"data.root={walker_dataset}",
        "data.synthesize=null",
        f"logger.tracking_uri={uri}",
        f"logger.artifact_root={out}/art",
        f"candidate={first.run_id}",
    ]
    decision = promote("tokenizer", load_promote_config(overrides))
    client = MlflowClient(uri)
    version = client.get_model_version("mmm-tokenizer", decision.version)
    registered_digest = sha256(first.best_checkpoint)
    assert version.tags["weights.sha256"] == registered_digest
    # The same weights promoted again (pipeline --force) are measured again in their own version,
    # never registered twice: a copy of the champion would become its own challenger.
    client.set_model_version_tag("mmm-tokenizer", decision.version, "metric.stale/metric", "1.0")
    again = promote("tokenizer", load_promote_config(overrides))
    assert (again.version, again.alias, again.promoted) == (decision.version, "champion", True)
    assert [v.version for v in client.search_model_versions("name='mmm-tokenizer'")] == [decision.version]
    retagged = client.get_model_version("mmm-tokenizer", decision.version).tags
    assert "metric.stale/metric" not in retagged and retagged["weights.sha256"] == registered_digest
    assert (
        retagged["metric.recon/mpjpe_root_aligned_mm"] == version.tags["metric.recon/mpjpe_root_aligned_mm"]
    )
    assert version.source == f"runs:/{first.run_id}/registered/mmm-tokenizer-{registered_digest[:12]}"
    assert version.tags["protocol.hash"] and '"split": "test"' in version.tags["protocol.settings"]
    assert f"**Protocol** `{version.tags['protocol.hash']}`" in version.description

    # A checkpoint copied outside the stage's output folder, resumed with another batch size
    # (allowed: the epoch restarts) and more steps.
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    foreign = elsewhere / "copy.ckpt"
    shutil.copyfile(first.last_checkpoint, foreign)
    before = sha256(foreign)
    resumed = train_stage1(
        stage1_config(
            walker_dataset,
            out,
            "trainer.max_steps=6",  # + the helpers' refine.steps=2: 8 steps in all
            "data.batch_size=4",
            "trainer.resume_restart_epoch=true",
        ),
        resume=str(foreign),
    )
    assert (
        sorted(p.name for p in elsewhere.iterdir()) == ["copy.ckpt"] and sha256(foreign) == before
    )  # nothing written beside it
    run_dir = Path(resumed.checkpoint_dir).parent
    assert (
        run_dir.parent == (out / "s1").resolve() and run_dir != Path(first.checkpoint_dir).parent
    )  # a new run folder of the stage
    assert torch.load(resumed.last_checkpoint, map_location="cpu", weights_only=True)["global_step"] == 8
    assert resumed.run_id == first.run_id  # the same MLflow run goes on, and re-uploads its checkpoints/

    # The run's checkpoints/best.ckpt is now another file; the registered version still loads its own copy.
    uploaded = client.download_artifacts(first.run_id, "checkpoints/best.ckpt", str(tmp_path / "dl"))
    assert sha256(uploaded) != registered_digest
    _, local, _ = resolve_checkpoint(
        f"models:/mmm-tokenizer/{decision.version}",
        uri,
        "mmm-stage1",
        str(out / "s1"),
        "tokenizer",
        "-",
        "stage1",
        cache_dir=str(tmp_path / "cache"),
    )
    assert sha256(local) == registered_digest

    # A registered copy altered in the store is refused when the version is loaded.
    stored = (
        Path(
            client.download_artifacts(
                first.run_id, f"registered/mmm-tokenizer-{registered_digest[:12]}", str(tmp_path / "dl2")
            )
        )
        / "best.ckpt"
    )
    artifact_root = Path(client.get_run(first.run_id).info.artifact_uri.removeprefix("file://"))
    frozen = artifact_root / "registered" / f"mmm-tokenizer-{registered_digest[:12]}" / "best.ckpt"
    assert sha256(stored) == sha256(frozen) == registered_digest
    altered = bytearray(frozen.read_bytes())
    altered[len(altered) // 2] ^= 0xFF  # same size, other content
    frozen.write_bytes(bytes(altered))
    with pytest.raises(FileNotFoundError, match="sha256"):
        resolve_checkpoint(
            f"models:/mmm-tokenizer/{decision.version}",
            uri,
            "mmm-stage1",
            str(out / "s1"),
            "tokenizer",
            "-",
            "stage1",
            cache_dir=str(tmp_path / "cache2"),
        )


@pytest.mark.slow
def test_an_unknown_candidate_is_named(stage1_run, walker_dataset):
    from mmm.registry.configs import load_promote_config
    from mmm.registry.promote import promote
    from mmm.resolve import ModelNotFound

    config = load_promote_config(
        [f"data.root={walker_dataset}", f"logger.tracking_uri={stage1_run['uri']}", "candidate=deadbeef"]
    )
    with pytest.raises(ModelNotFound, match=r"candidate=deadbeef: no such run in the tracking store sqlite:"):
        promote("tokenizer", config)


# -- item 10: a resume that would silently change the run is refused
# ---------------------------------------------
@pytest.mark.slow
def test_resume_refuses_another_batch_size_or_learning_rate_and_writes_nothing(stage1_run, walker_dataset):
    from mmm.training.stage1 import train_stage1

    out, first = stage1_run["out"], stage1_run["result"]
    last = Path(first.last_checkpoint)
    before = {p.name: sha256(p) for p in last.parent.iterdir()}
    with pytest.raises(
        ValueError, match=r"batch_size 8 in the checkpoint, 4 now.*trainer.resume_restart_epoch=true"
    ):
        train_stage1(
            stage1_config(walker_dataset, out, "trainer.max_steps=8", "data.batch_size=4"), resume=str(last)
        )
    with pytest.raises(ValueError, match=r"optim.lr: 0.001 in the checkpoint, 0.0005 now"):
        train_stage1(
            stage1_config(walker_dataset, out, "trainer.max_steps=8", "optim.lr=0.0005"), resume=str(last)
        )
    # A final rate drop that would already be behind the checkpoint's step (4): refused.
    with pytest.raises(
        ValueError,
        match=r"no drop in the checkpoint's fit of 6 steps and its drop at step 2 of this fit of 10",
    ):
        train_stage1(
            stage1_config(walker_dataset, out, "trainer.max_steps=8", "optim.final_share=0.75"),
            resume=str(last),
        )
    # Another model size: refused before Lightning's load fails halfway and marks the run FAILED.
    with pytest.raises(
        ValueError, match=r"weights do not fit the model this config builds \(.*of another shape \(tokenizer"
    ) as refused:
        train_stage1(
            stage1_config(walker_dataset, out, "trainer.max_steps=8", "model.tokenizer.code_dim=16"),
            resume=str(last),
        )
    assert "resume with the settings it was trained with" in str(refused.value)
    # Nothing left to train (the checkpoint is at the step the fit ends at): refused, not a launch
    # that uploads the same checkpoints again and reports no validation.
    step = torch.load(last, map_location="cpu", weights_only=True)["global_step"]
    with pytest.raises(
        ValueError, match=rf"nothing to resume: the checkpoint is at step {step} and this fit"
    ):
        train_stage1(
            stage1_config(walker_dataset, out, f"trainer.max_steps={step}", "refine.steps=0"),
            resume=str(last),
        )
    # A copy outside the stage's folder would continue in a new run folder: refused, none is left.
    runs = sorted(p.name for p in (out / "s1").iterdir())
    foreign = out / "elsewhere" / "copy.ckpt"
    foreign.parent.mkdir(exist_ok=True)
    shutil.copyfile(last, foreign)
    with pytest.raises(ValueError, match="weights do not fit"):
        train_stage1(
            stage1_config(walker_dataset, out, "trainer.max_steps=8", "model.tokenizer.code_dim=16"),
            resume=str(foreign),
        )
    assert sorted(p.name for p in (out / "s1").iterdir()) == runs
    assert {p.name: sha256(p) for p in last.parent.iterdir()} == before
    assert MlflowClient(stage1_run["uri"]).get_run(first.run_id).info.status == "FINISHED"


def test_a_changed_global_batch_is_refused_unless_the_epoch_restarts_and_the_same_one_resumes():
    from mmm.callbacks.checkpoints import RunState

    def checkpoint():
        return {
            "data_position": {"batch_size": 8, "world_size": 1},
            "loops": {"fit_loop": {"state_dict": {"combined_loader": [{"epoch": 3, "batches": 5}]}}},
        }

    module = SimpleNamespace(hparams={}, state_dict=dict)
    with pytest.raises(ValueError, match=r"global batch \(world_size 1 in the checkpoint, 2 now\)"):
        RunState(batch_size=8).check_resume(SimpleNamespace(world_size=2), module, checkpoint())
    with pytest.raises(
        ValueError, match="batch_size 8 in the checkpoint, 2 now; world_size 1 in the checkpoint, 2"
    ):
        RunState(batch_size=2).check_resume(SimpleNamespace(world_size=2), module, checkpoint())
    restarted = checkpoint()
    RunState(batch_size=8, restart_epoch=True).on_load_checkpoint(
        SimpleNamespace(world_size=2), module, restarted
    )
    assert restarted["loops"]["fit_loop"]["state_dict"]["combined_loader"] == [{"epoch": 3, "batches": 0}]
    for batch_size, world_size in (
        (8, 1),
        (4, 2),
        (2, 4),
    ):  # the same global batch: the position carries over
        same = checkpoint()
        RunState(batch_size=batch_size).check_resume(SimpleNamespace(world_size=world_size), module, same)
        assert same == checkpoint()


def test_a_resume_that_moves_the_final_rate_drop_across_its_step_is_refused(caplog):
    from mmm.callbacks.checkpoints import RunState

    quarter = {"milestones": [], "final_share": 0.25}

    def resume(step: int, max_steps: int, optim: dict = quarter, recorded: int | None = 1500):
        checkpoint = {"global_step": step, "hyper_parameters": {"optim": quarter}}
        if recorded is not None:
            checkpoint["schedule_steps"] = recorded
        module = SimpleNamespace(hparams={"optim": optim}, state_dict=dict)
        RunState().check_resume(SimpleNamespace(world_size=1, max_steps=max_steps), module, checkpoint)

    # 1,500 steps with the last quarter at rate x gamma: the drop at step 1,125. Resumed at 1,400
    # for 3,000 steps, the drop would move to 2,250 and the rate go back up tenfold.
    with pytest.raises(ValueError) as refused:
        resume(1400, 3000)
    assert str(refused.value) == (
        "cannot resume at step 1400: optim.final_share places its drop at step 1125 of the checkpoint's "
        "fit of 1500 steps and its drop at step 2250 of this fit of 3000 steps, so the learning rate "
        "would change at once; resume with a fit of 1500 steps (trainer.max_steps, with refine.steps "
        "for a tokenizer), or keep the checkpoint's schedule with optim.milestones=[1125] "
        "optim.final_share=0 and any trainer.max_steps"
    )
    with pytest.raises(ValueError, match="at step 1000: .* drop at step 900 of this fit of 1200"):
        resume(1000, 1200)  # shortened: the rate would drop at once
    with pytest.raises(ValueError, match="and no drop in this fit of 3000 steps"):
        resume(1400, 3000, {"milestones": [], "final_share": 0.0})
    # The fix the message gives, the same count, a checkpoint from before the count was recorded,
    # and a drop still to come on both sides (said in the log): resumed.
    resume(1400, 3000, {"milestones": [1125], "final_share": 0.0})
    resume(1400, 1500)
    resume(1400, 3000, recorded=None)
    with caplog.at_level(logging.INFO, logger="mmm.callbacks.checkpoints"):
        resume(1000, 3000)
    assert "resuming at step 1000: optim.final_share places its drop at step 1125 of the" in caplog.text


@pytest.mark.slow
def test_stage2_resume_with_another_stage1_model_is_refused_naming_both(trained, tmp_path, monkeypatch):
    import mmm.training.common as common
    from mmm.training.configs import load_stage2_config
    from mmm.training.stage2 import train_stage2

    walker = trained["walker"]
    other = train_tiny_stage1(walker, tmp_path / "other", "seed=1")  # same codebook shape, other weights
    recorded = torch.load(trained["checkpoint"], map_location="cpu", weights_only=True)["hyper_parameters"][
        "stage1"
    ]["identity"]
    copy = tmp_path / "copy" / "stage2.ckpt"
    copy.parent.mkdir()
    shutil.copyfile(trained["checkpoint"], copy)
    cfg = load_stage2_config(stage2_overrides(walker, tmp_path, stage1=other.best_checkpoint))
    reads, load = [], common.load_checkpoint  # the resumed checkpoint is read once for all its checks
    monkeypatch.setattr(common, "load_checkpoint", lambda path, *a: reads.append(path) or load(path, *a))
    with pytest.raises(ValueError, match="trained on stage-1 model") as refused:
        train_stage2(cfg, resume=str(copy))
    assert [Path(p).resolve() for p in reads] == [copy.resolve()]
    message = str(refused.value)
    from mmm.fingerprint import tensors_fingerprint
    from mmm.tokenizer.load import load_tokenizer_checkpoint

    assert (
        recorded in message
        and tensors_fingerprint(load_tokenizer_checkpoint(other.best_checkpoint).state_dict()) in message
    )
    assert not (tmp_path / "s2").exists() or not any((tmp_path / "s2").glob("*/checkpoints/*.ckpt"))


# -- item 9: like with like; unmeasured metrics never promote; criteria validated
# --------------------------------
@pytest.fixture
def client(tmp_path):
    return MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")


def add(client, name, fid, protocol=None):
    tags = version_tags({"generated/fid": fid}, "d1", "e1", "cfg", protocol=protocol)
    return register_version(client, name, "runs:/0123456789abcdef0123456789abcdef/bundle", None, tags).version


CRITERIA = [Criterion("generated/fid", "min", 0.0)]


@pytest.mark.slow
@pytest.mark.parametrize("fid", [float("nan"), float("inf"), None])
def test_unmeasured_metrics_never_promote_even_without_a_champion(client, fid):
    tags = version_tags({"generated/fid": fid} if fid is not None else {}, "d1", "e1", "cfg")
    version = register_version(
        client, "m", "runs:/0123456789abcdef0123456789abcdef/bundle", None, tags
    ).version
    decision = promote_version(client, "m", version, CRITERIA)
    assert (decision.promoted, decision.alias) == (False, "challenger")
    assert decision.reason.startswith("not measured: generated/fid missing")
    assert client.get_registered_model("m").aliases == {"challenger": version}


@pytest.mark.slow
def test_a_candidate_measured_with_another_protocol_is_not_compared(client):
    paper = {"split": "test", "protocol.replications": 20, "protocol.seed": 0, "evaluator": "e1"}
    champion = add(client, "m", 0.5, paper)
    assert promote_version(client, "m", champion, CRITERIA).promoted
    quick = add(client, "m", 0.1, {**paper, "protocol.replications": 2})
    decision = promote_version(client, "m", quick, CRITERIA)
    assert (decision.promoted, decision.alias) == (False, "challenger")
    assert (
        "measured with another protocol than the champion (protocol.replications 2 vs 20)" in decision.reason
    )
    assert client.get_model_version_by_alias("m", "champion").version == champion
    same = add(client, "m", 0.1, dict(paper))
    assert promote_version(client, "m", same, CRITERIA).promoted


@pytest.mark.parametrize(
    "criterion, complaint",
    [
        (
            "{metric: generated/fid, mode: best, margin: 0.0}",
            "criteria.text2motion[0].mode='best' must be min",
        ),
        (
            "{metric: generated/fid, mode: min, margin: -0.1}",
            "criteria.text2motion[0].margin=-0.1 must be a finite number >= 0",
        ),
        (
            "{metric: generated/fid, mode: min, margin: nan}",
            "criteria.text2motion[0].margin=nan must be a finite number >= 0",
        ),
        ("", "criteria.text2motion is empty: a candidate would become champion compared on nothing"),
    ],
)
def test_criteria_are_validated_when_the_config_is_loaded(criterion, complaint):
    from mmm.registry.configs import load_promote_config

    with pytest.raises(ConfigError) as refused:
        load_promote_config([f"criteria.text2motion=[{criterion}]"])
    assert complaint in str(refused.value)
    with pytest.raises(ValueError, match="mode='best'"):
        promote_version(None, "m", "1", [Criterion("generated/fid", "best")])


def _promote_rounds(uri: str, rounds: int, version: str, barrier) -> None:
    """One of two racing promoters: in each round, wait for the other, then promote `version` of m<round>."""
    client = MlflowClient(uri)
    for r in range(rounds):
        barrier.wait(timeout=60)
        promote_version(client, f"m{r}", version, CRITERIA)


@pytest.mark.slow
def test_two_concurrent_promotions_always_leave_the_better_model_champion(tmp_path):
    uri, rounds = f"sqlite:///{tmp_path}/mlflow.db", 8
    client = MlflowClient(uri)
    for r in range(rounds):
        promote_version(client, f"m{r}", add(client, f"m{r}", 0.9), CRITERIA)  # v1: the champion both beat
        assert (str(add(client, f"m{r}", 0.1)), str(add(client, f"m{r}", 0.5))) == (
            "2",
            "3",
        )  # v2 the better, v3 the worse
    context = multiprocessing.get_context("spawn")
    barrier = context.Barrier(2)
    racers = [
        context.Process(target=_promote_rounds, args=(uri, rounds, version, barrier))
        for version in ("2", "3")
    ]
    for p in racers:
        p.start()
    for p in racers:
        p.join(timeout=240)
    assert [p.exitcode for p in racers] == [0, 0]
    champions = [str(client.get_model_version_by_alias(f"m{r}", "champion").version) for r in range(rounds)]
    assert champions == ["2"] * rounds


# -- item 11: concurrency of run folders, pipelines and token caches
# ---------------------------------------------
def _fake_run(output_dir: Path, name: str, age: float) -> Path:
    last = output_dir / name / "checkpoints" / "last.ckpt"
    last.parent.mkdir(parents=True)
    last.write_bytes(b"x")
    os.utime(last, (time.time() - age, time.time() - age))
    return last


def test_resume_last_skips_a_run_another_process_is_writing(tmp_path, monkeypatch):
    from mmm.training.runs import RunLock, claim_run_directory, find_last_checkpoint, resume_target

    for var in (
        "MMM_RUN_DIR",
        "TORCHELASTIC_RUN_ID",
        "SLURM_JOB_ID",
        "SLURM_STEP_ID",
        "RANK",
        "LOCAL_RANK",
        "SLURM_PROCID",
        "NODE_RANK",
    ):
        monkeypatch.delenv(var, raising=False)
    older, newer = _fake_run(tmp_path, "older", 100), _fake_run(tmp_path, "newer", 10)
    assert find_last_checkpoint(tmp_path) == newer
    held = RunLock.try_acquire(newer.parent.parent)  # a training still writing the newest run
    try:
        assert find_last_checkpoint(tmp_path) == older
        assert resume_target("last", tmp_path) == (older.resolve(), older.parent.parent.resolve())
        with pytest.raises(FileExistsError, match="still training in this run folder"):
            claim_run_directory(newer.parent.parent, resuming=True)
        other = RunLock.try_acquire(older.parent.parent)
        with pytest.raises(FileNotFoundError, match="still being written by another training"):
            find_last_checkpoint(tmp_path)
        other.release()
    finally:
        held.release()
    assert find_last_checkpoint(tmp_path) == newer  # released: resumable again


def test_two_launches_in_one_allocation_get_different_run_folders(tmp_path, monkeypatch):
    from mmm.training.runs import run_directory

    monkeypatch.delenv("MMM_RUN_DIR", raising=False)
    monkeypatch.delenv("TORCHELASTIC_RUN_ID", raising=False)
    monkeypatch.setenv("SLURM_JOB_ID", "4242")
    folders = {}
    for step in ("0", "1"):
        monkeypatch.setenv("SLURM_STEP_ID", step)
        folders[step] = {run_directory(tmp_path) for _rank in range(2)}  # every rank of a launch agrees
    assert all(len(f) == 1 for f in folders.values()) and folders["0"] != folders["1"]
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "shared-rdzv")
    ports = set()
    for port in ("29500", "29501"):
        monkeypatch.setenv("MASTER_PORT", port)
        ports.add(run_directory(tmp_path))
    assert len(ports) == 2


@pytest.mark.slow
def test_pipelines_on_one_state_file_run_one_at_a_time(tmp_path):
    from mmm.pipeline.runner import Context, Step, run_steps, state_lock

    state_file = tmp_path / "state.json"
    ran = []
    step = Step("only", lambda ctx: {"x": 1}, lambda ctx: ran.append(time.time()) or {"done": True})
    ctx = Context(cfg=None, tracking_uri=f"sqlite:///{tmp_path}/mlflow.db")
    with state_lock(state_file):
        worker = threading.Thread(target=run_steps, args=("t", [step], ctx, state_file))
        worker.start()
        worker.join(timeout=3)
        assert worker.is_alive() and ran == [] and not state_file.exists()  # waits for the holder
    worker.join(timeout=60)
    assert not worker.is_alive() and len(ran) == 1 and state_file.exists()


@pytest.mark.slow
def test_a_token_cache_finished_by_another_process_meanwhile_is_kept(trained, tmp_path, monkeypatch):
    """Two `mmm tokenize` at once: the second to finish finds the first one's folder in place."""
    from mmm.data import tokens as tokens_module
    from mmm.tokenizer.load import load_tokenizer_checkpoint

    tokenizer = load_tokenizer_checkpoint(next((trained["out"] / "s1").glob("*/checkpoints/best.ckpt")))
    folder = tmp_path / "tokens" / "abc-def"
    real_replace = os.replace

    def replace(src, dst):
        if Path(dst) == folder and not folder.exists():  # the other process renames its complete copy first
            shutil.copytree(src, folder)
        return real_replace(src, dst)

    monkeypatch.setattr(tokens_module.os, "replace", replace)
    cache = tokens_module.tokenize_dataset(tokenizer, trained["walker"], folder, progress=False)
    assert len(cache) == 30 and sorted(p.name for p in folder.iterdir()) == ["meta.json", "tokens.npz"]
    assert [p.name for p in folder.parent.iterdir()] == ["abc-def"]  # no temporary folder left


# -- item 12: pipeline keys
# -------------------------------------------------------------------------------------
def test_dataset_fingerprint_notices_a_rewrite_that_keeps_size_and_mtime(tmp_path):
    from mmm.fingerprint import dataset_fingerprint
    from tests.helpers import write_walker_dataset

    root = write_walker_dataset(tmp_path / "ds", num_clips=10)
    first = dataset_fingerprint(root)
    path = root / "new_joint_vecs" / "000001.npy"
    stat = path.stat()
    data = np.load(path)
    data[0, 0] += 1.0
    np.save(path, data)  # same shape: same size
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns
    assert dataset_fingerprint(root) != first
    (root / "labels").mkdir()
    (root / "labels" / "000001.json").write_text("{}")
    plain = dataset_fingerprint(root)
    with_labels = dataset_fingerprint(root, ("labels", "new_joints"))
    (root / "labels" / "000001.json").write_text('{"x": 1}')
    assert (
        dataset_fingerprint(root) == plain
        and dataset_fingerprint(root, ("labels", "new_joints")) != with_labels
    )


def test_dataset_fingerprint_is_the_hash_of_its_files_in_order(tmp_path):
    """The value written out by hand: split files, then each folder's files by name, each line
    `relative path:sha256 of the bytes`; a second call (from the stat cache) gives the same."""
    import hashlib

    from mmm.fingerprint import dataset_fingerprint
    from tests.helpers import write_walker_dataset

    root = write_walker_dataset(tmp_path / "ds", num_clips=6)
    (root / "labels").mkdir()
    for name in ("b.json", "a.json", "a0.json"):
        (root / "labels" / name).write_text(name)
    expected = hashlib.sha256()
    names = [n for n in ("train.txt", "val.txt", "test.txt", "Mean.npy", "Std.npy") if (root / n).exists()]
    for part in ("new_joint_vecs", "texts", "labels"):
        names += [f"{part}/{n}" for n in sorted(os.listdir(root / part))]
    for name in names:
        expected.update(f"{name}:{hashlib.sha256((root / name).read_bytes()).hexdigest()}\n".encode())
    assert dataset_fingerprint(root, ("labels",)) == expected.hexdigest()[:16]
    assert dataset_fingerprint(root, ("labels",)) == expected.hexdigest()[:16]  # from the cache


def test_step_keys_include_the_resolved_config_and_the_code_version(walker_dataset, tmp_path, monkeypatch):
    from mmm.config import to_object
    from mmm.pipeline import steps
    from mmm.pipeline.configs import load_pipeline_config
    from mmm.pipeline.runner import Context, step_key
    from mmm.registry import versions as promotion

    conf = tmp_path / "conf"
    shutil.copytree(os.environ["MMM_CONF_DIR"], conf)
    monkeypatch.setenv("MMM_CONF_DIR", str(conf))

    def key() -> str:
        cfg = to_object(
            load_pipeline_config(
                [f"data.root={walker_dataset}", "data.synthesize=null", f"state_file={tmp_path}/s.json"]
            )
        )
        step = steps.step_stage1()
        return step_key(step.name, step.inputs(Context(cfg, f"sqlite:///{tmp_path}/mlflow.db")))

    first = key()
    assert key() == first
    text = (conf / "train_stage1.yaml").read_text()
    assert "\nseed: 0\n" in text
    # A default changed in the config files (no override names it): the resolved config differs.
    (conf / "train_stage1.yaml").write_text(text.replace("\nseed: 0\n", "\nseed: 7\n"))
    changed = key()
    assert changed != first
    monkeypatch.setattr(promotion, "code_version", lambda: "0123abc")
    assert key() != changed

"""Writes and caches that a later run trusts: never a half-written or stale file under a real name.

The model download cache (content-keyed, verified), atomic checkpoint saves (also when the
training is SIGKILLed during one), `--overwrite` of a sample folder, the bundle cache's fills.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

import mmm.generation.outputs as outputs
from mmm.atomic import atomic_write, atomic_write_bytes
from mmm.resolve import ArtifactMismatch, download_artifact, log_artifact_with_digest, sha256_tag


# -- the shared helper ------------------------------------------------------------------------------
def test_atomic_write_keeps_the_old_file_when_the_write_fails(tmp_path):
    path = tmp_path / "stats.json"
    atomic_write_bytes(path, b'{"old": 1}')
    with pytest.raises(RuntimeError, match="disk on fire"):
        with atomic_write(path, "wb") as fh:
            fh.write(b'{"new": ')  # half of the new content, then the writer dies
            raise RuntimeError("disk on fire")
    assert path.read_bytes() == b'{"old": 1}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stats.json"]  # no temporary file left
    assert oct(path.stat().st_mode & 0o777) == oct(0o644)


# -- the model download cache -----------------------------------------------------------------------
@pytest.fixture
def store(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    client = MlflowClient(uri)
    experiment = client.create_experiment("cache-test", artifact_location=(tmp_path / "art").as_uri())
    run_id = client.create_run(experiment).info.run_id
    return {
        "uri": uri,
        "client": client,
        "run_id": run_id,
        "cache": tmp_path / "cache",
        "files": tmp_path / "files",
    }


def _upload(store, content: bytes, tagged: bool = True) -> None:
    """Upload `content` as the run's checkpoints/best.ckpt (as a training or a resume does)."""
    store["files"].mkdir(exist_ok=True)
    local = store["files"] / "best.ckpt"
    local.write_bytes(content)
    if tagged:
        log_artifact_with_digest(store["client"], store["run_id"], local, "checkpoints")
    else:
        store["client"].log_artifact(store["run_id"], str(local), "checkpoints")


def _leftovers(cache: Path) -> list[str]:
    return [p.name for p in cache.iterdir() if p.name.startswith(".")] if cache.exists() else []


@pytest.mark.slow
def test_truncated_cached_file_is_fetched_again(store, monkeypatch):
    import mlflow.artifacts

    content = np.random.default_rng(0).bytes(50_000)
    _upload(store, content)
    assert store["client"].get_run(store["run_id"]).data.tags[sha256_tag("checkpoints/best.ckpt")]
    first = Path(download_artifact(store["uri"], store["run_id"], "checkpoints/best.ckpt", store["cache"]))
    assert first.read_bytes() == content
    first.write_bytes(content[:20_000])  # a copy cut short (a full disk, an older version's kill)

    again = Path(download_artifact(store["uri"], store["run_id"], "checkpoints/best.ckpt", store["cache"]))
    assert again.read_bytes() == content

    # A complete cached copy is used as it is: no third download.
    calls = []
    real = mlflow.artifacts.download_artifacts
    monkeypatch.setattr(
        mlflow.artifacts, "download_artifacts", lambda *a, **k: calls.append(k) or real(*a, **k)
    )
    assert (
        Path(
            download_artifact(store["uri"], store["run_id"], "checkpoints/best.ckpt", store["cache"])
        ).read_bytes()
        == content
    )
    assert calls == []
    assert _leftovers(store["cache"]) == []


@pytest.mark.slow
@pytest.mark.parametrize("tagged", [True, False], ids=["recorded-sha256", "untagged"])
def test_reuploaded_checkpoint_is_never_served_stale(store, tagged):
    """A --resume uploads a new best.ckpt under the same run and name, of the same size."""
    before, after = b"A" * 4096, b"B" * 4096
    _upload(store, before, tagged)
    assert (
        Path(
            download_artifact(store["uri"], store["run_id"], "checkpoints/best.ckpt", store["cache"])
        ).read_bytes()
        == before
    )
    _upload(store, after, tagged)
    assert (
        Path(
            download_artifact(store["uri"], store["run_id"], "checkpoints/best.ckpt", store["cache"])
        ).read_bytes()
        == after
    )
    assert _leftovers(store["cache"]) == []


@pytest.mark.slow
def test_a_download_that_does_not_match_the_recorded_digest_is_refused(store):
    _upload(store, b"weights" * 100)
    with pytest.raises(
        ArtifactMismatch, match=r"the download has sha256 [0-9a-f]{64}, the recorded sha256 is 0{64}"
    ):
        download_artifact(
            store["uri"], store["run_id"], "checkpoints/best.ckpt", store["cache"], sha256="0" * 64
        )
    assert not (store["cache"] / "by-sha256" / ("0" * 64)).exists()
    assert _leftovers(store["cache"]) == []


# -- checkpoint saves -------------------------------------------------------------------------------
def _trainer_checkpoint_io(tmp_path):
    from mmm.training.common import build_trainer
    from mmm.training.configs import TrainerConfig

    trainer = build_trainer(TrainerConfig(max_steps=1, enable_progress_bar=False), [], None, str(tmp_path))
    return trainer.strategy.checkpoint_io


def test_checkpoint_save_is_atomic_in_its_own_folder(tmp_path, monkeypatch):
    io = _trainer_checkpoint_io(tmp_path)
    folder = tmp_path / "checkpoints"
    last = folder / "last.ckpt"
    io.save_checkpoint({"global_step": 10, "w": torch.ones(1000)}, last)

    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    written_to = []
    real_save = torch.save

    def dies_halfway(obj, f, *args, **kwargs):
        written_to.extend(p.name for p in folder.iterdir() if p.name != "last.ckpt")  # where the bytes go
        real_save(obj, f, *args, **kwargs)
        f.truncate(f.tell() // 2)  # only part of the data ...
        raise OSError(28, "No space left on device")  # ... then the save dies

    monkeypatch.setattr(torch, "save", dies_halfway)
    with pytest.raises(OSError, match="No space left"):
        io.save_checkpoint({"global_step": 20, "w": torch.zeros(1000)}, last)
    monkeypatch.setattr(torch, "save", real_save)

    kept = torch.load(last, map_location="cpu", weights_only=True)
    assert kept["global_step"] == 10 and torch.equal(kept["w"], torch.ones(1000))  # the previous complete one
    assert sorted(p.name for p in folder.iterdir()) == ["last.ckpt"]  # no half file, under any name
    assert len(written_to) == 1 and written_to[0].startswith(
        ".last.ckpt."
    )  # a temporary file beside it, not in $TMPDIR

    io.save_checkpoint({"global_step": 30, "w": torch.full((1000,), 3.0)}, last)
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == 30
    assert synced  # the file (and its folder) reached the disk before the rename counted


@pytest.mark.slow
def test_training_killed_during_a_checkpoint_save_resumes_from_the_previous_one(walker_dataset, tmp_path):
    """SIGKILL while last.ckpt is being rewritten (a test hook holds each save open for 2 s before
    its rename), then `mmm train stage1 --resume last`: the previous complete last.ckpt is intact
    and the training finishes."""
    out = tmp_path / "run"
    overrides = [
        f"data.root={walker_dataset}",
        "data.synthesize=null",
        "data.batch_size=8",
        "model.tokenizer.width=16",
        "model.tokenizer.num_codes=32",
        "trainer.max_steps=6",
        "refine.steps=0",
        "trainer.val_check_interval=2",
        "trainer.enable_progress_bar=false",
        "callbacks.preview_clips=0",
        "callbacks.usage_plot=false",
        f"output_dir={out}/s1",
        f"logger.tracking_uri=sqlite:///{out}/mlflow.db",
        f"logger.artifact_root={out}/art",
    ]
    train = [sys.executable, "-m", "mmm.cli", "train", "stage1", *overrides]
    proc = subprocess.Popen(
        train,
        env={**os.environ, "MMM_TEST_CHECKPOINT_SAVE_DELAY": "2"},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    saving = []
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            lasts = list((out / "s1").glob("*/checkpoints/last.ckpt"))
            saving = list((out / "s1").glob("*/checkpoints/.last.ckpt.*.tmp"))
            if lasts and saving:
                break  # a complete last.ckpt exists and the next one is being written
            time.sleep(0.05)
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert saving and proc.returncode == -signal.SIGKILL, (
        f"no save caught in progress (exit {proc.returncode}): {proc.stderr.read().decode()[-3000:]}"
    )
    checkpoints = saving[0].parent
    kept = torch.load(checkpoints / "last.ckpt", map_location="cpu", weights_only=True)
    assert kept["global_step"] == 2  # the save at step 4 never replaced it

    resumed = subprocess.run([*train, "--resume", "last"], capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert torch.load(checkpoints / "last.ckpt", map_location="cpu", weights_only=True)["global_step"] == 6
    assert not list(checkpoints.glob(".*.tmp"))  # the killed save's temporary file was cleared
    assert len(list((out / "s1").iterdir())) == 1  # the resume went on in the same run folder


# -- --overwrite of a sample folder -----------------------------------------------------------------
def _samples(n: int, tag: str, frames: int = 12) -> list[dict]:
    from mmm.motion.features import joints_to_features
    from tests.helpers import turning_walker

    joints = turning_walker(frames=frames + 1).numpy().astype(np.float32)
    features = joints_to_features(joints)
    return [
        {
            "features": features,
            "joints": joints[: features.shape[0]],
            "caption": f"{tag} {k}",
            "meta": {"run": tag, "sample": k},
        }
        for k in range(n)
    ]


def _quick_sample(folder, features, joints, caption, meta, skeleton, reference=None, spans=None):
    """What _write_sample leaves, without rendering (the folder's content is all these tests read)."""
    folder.mkdir(parents=True)
    np.save(folder / "features.npy", features)
    (folder / "meta.json").write_text(json.dumps(meta))


def _runs(out: Path) -> dict[str, str]:
    return {p.name: json.loads((p / "meta.json").read_text())["run"] for p in sorted(out.iterdir())}


def _siblings(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name != out.name)


def test_overwrite_with_fewer_samples_replaces_the_whole_folder(tmp_path):
    from mmm.motion.skeleton import T2M_SKELETON

    out = tmp_path / "gen"
    outputs.write_samples(out, _samples(3, "old"), T2M_SKELETON)
    assert _runs(out) == {"0": "old", "1": "old", "2": "old"}
    # readable by others like every other output (its staging folder was mkdtemp's 0700)
    umask = os.umask(0)
    os.umask(umask)
    assert (out.stat().st_mode & 0o777, (out / "0").stat().st_mode & 0o777) == (0o755, 0o777 & ~umask)
    with pytest.raises(FileExistsError, match="pass --overwrite"):
        outputs.write_samples(out, _samples(1, "new"), T2M_SKELETON)
    folders = outputs.write_samples(out, _samples(1, "new"), T2M_SKELETON, overwrite=True)
    assert folders == [out / "0"]
    assert _runs(out) == {"0": "new"}  # no stale gen/1, gen/2 from the run with more samples
    assert {"features.npy", "joints.npy", "motion.gif", "motion.bvh", "meta.json"} <= {
        p.name for p in (out / "0").iterdir()
    }
    assert _siblings(out) == []  # no temporary folder left beside it


@pytest.mark.slow
def test_cli_generate_overwrite_with_fewer_samples(trained, tmp_path, capsys):
    from mmm.cli import main

    out = tmp_path / "gen"
    common = [
        "generate",
        "--text",
        "a person walks forward",
        "--length",
        "60",
        "--model",
        trained["checkpoint"],
        "--tracking-uri",
        trained["uri"],
        "--out",
        str(out),
    ]
    assert main([*common, "--num-samples", "3", "--seed", "1", "--trace"]) == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["0", "1", "2", "decoding_trace.png"]
    assert (
        main([*common, "--num-samples", "1", "--seed", "2"]) == 2
    )  # without --overwrite: refused, nothing changed
    assert "pass --overwrite" in capsys.readouterr().err and sorted(p.name for p in out.iterdir()) == [
        "0",
        "1",
        "2",
        "decoding_trace.png",
    ]
    assert main([*common, "--num-samples", "1", "--seed", "2", "--overwrite"]) == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["0"]  # no stale gen/1, gen/2 or old trace
    assert json.loads((out / "0" / "meta.json").read_text())["seed"] == 2
    assert _siblings(out) == []


def test_interrupted_overwrite_leaves_the_old_folder(tmp_path, monkeypatch):
    from mmm.motion.skeleton import T2M_SKELETON

    monkeypatch.setattr(outputs, "_write_sample", _quick_sample)
    out = tmp_path / "gen"
    outputs.write_samples(out, _samples(2, "old"), T2M_SKELETON)

    # 1. the second sample fails while being written
    def fails_on_second(folder, *args):
        if folder.name == "1":
            raise KeyboardInterrupt
        _quick_sample(folder, *args)

    monkeypatch.setattr(outputs, "_write_sample", fails_on_second)
    with pytest.raises(KeyboardInterrupt):
        outputs.write_samples(out, _samples(2, "new"), T2M_SKELETON, overwrite=True)
    assert _runs(out) == {"0": "old", "1": "old"} and _siblings(out) == []

    # 2. every sample is written, and the move into place is cut off after its first rename
    monkeypatch.setattr(outputs, "_write_sample", _quick_sample)
    moves = []

    def cut_after_first(real):
        def rename(src, dst, *args, **kwargs):
            if (
                sys._getframe(1).f_globals.get("__name__") == outputs.__name__
            ):  # only write_samples' own moves
                moves.append((src, dst))
                if len(moves) == 2:
                    raise OSError(5, "Input/output error")
            return real(src, dst, *args, **kwargs)

        return rename

    monkeypatch.setattr(os, "rename", cut_after_first(os.rename))
    monkeypatch.setattr(os, "replace", cut_after_first(os.replace))
    with pytest.raises(OSError, match="Input/output error"):
        outputs.write_samples(out, _samples(2, "new"), T2M_SKELETON, overwrite=True)
    monkeypatch.undo()
    assert _runs(out) == {"0": "old", "1": "old"}  # all old: never gen/0 new beside gen/1 old
    assert _siblings(out) == []


def test_overwrite_refuses_a_folder_that_holds_more_than_samples(tmp_path, monkeypatch):
    from mmm.motion.skeleton import T2M_SKELETON

    monkeypatch.setattr(outputs, "_write_sample", _quick_sample)
    out = tmp_path / "project"
    outputs.write_samples(out, _samples(1, "old"), T2M_SKELETON)
    (out / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match=r"project holds notes.txt besides samples"):
        outputs.write_samples(out, _samples(1, "new"), T2M_SKELETON, overwrite=True)
    assert (out / "notes.txt").read_text() == "mine" and json.loads((out / "0" / "meta.json").read_text())[
        "run"
    ] == "old"
    assert _siblings(out) == []


# -- the bundle cache ---------------------------------------------------------------------------------
def _bundle_source(tmp_path) -> Path:
    """A stand-in for a logged bundle's files (the cache copies folders; what they hold is not read here)."""
    src = tmp_path / "logged" / "bundle"
    (src / "artifacts").mkdir(parents=True)
    (src / "MLmodel").write_text("flavors: {}\n")
    (src / "artifacts" / "transformer.ckpt").write_bytes(os.urandom(200_000))
    return src


@pytest.mark.slow
def test_concurrent_bundle_cache_fills_share_one_complete_copy(tmp_path, monkeypatch):
    import mlflow.artifacts

    from mmm import resolve

    src = _bundle_source(tmp_path)
    dst = tmp_path / "cache" / "bundles" / "abc123"
    downloads = []
    real = mlflow.artifacts.download_artifacts
    first_started = threading.Event()

    def slow_download(*args, **kwargs):
        downloads.append(kwargs["dst_path"])
        first_started.set()
        time.sleep(1.0)  # a large bundle: the second fill starts while this one is under way
        return real(*args, **kwargs)

    monkeypatch.setattr(mlflow.artifacts, "download_artifacts", slow_download)
    got, errors = {}, []

    def fill(name):
        try:
            got[name] = resolve._download(str(src), f"sqlite:///{tmp_path}/m.db", dst)
            got[name + "-inode"] = (got[name] / "artifacts" / "transformer.ckpt").stat().st_ino
        except BaseException as e:  # reported below
            errors.append(e)

    first = threading.Thread(target=fill, args=("a",))
    first.start()
    assert first_started.wait(30)
    second = threading.Thread(target=fill, args=("b",))
    second.start()
    first.join(60)
    second.join(60)
    assert errors == []
    assert got["a"] == got["b"] and got["a-inode"] == got["b-inode"]  # both use the one complete copy
    assert len(downloads) == 1  # the second waited for the first and took its copy
    assert (got["a"] / "artifacts" / "transformer.ckpt").read_bytes() == (
        src / "artifacts" / "transformer.ckpt"
    ).read_bytes()
    assert (dst / resolve.COMPLETE).is_file()

    # A later fill of a complete copy keeps it: nothing deleted, nothing downloaded.
    assert resolve._download(str(src), f"sqlite:///{tmp_path}/m.db", dst) == got["a"]
    assert (got["a"] / "artifacts" / "transformer.ckpt").stat().st_ino == got["a-inode"] and len(
        downloads
    ) == 1
    assert sorted(p.name for p in dst.parent.iterdir()) == [".abc123.lock", "abc123"]  # no temporary folders


def test_load_context_leaves_no_temporary_folders(tmp_path, monkeypatch):
    """A CLIP bundle's load_context (its text files travel in the bundle): nothing is left in $TMPDIR."""
    import tempfile
    from types import SimpleNamespace

    from mmm.generation.model import TextToMotion
    from mmm.registry.bundle import TextToMotionPyfunc

    files = tmp_path / "bundle" / "artifacts"
    files.mkdir(parents=True)
    torch.save(
        {
            "hyper_parameters": {
                "text_encoder": {
                    "name": "clip-vit-b32",
                    "identity": "x",
                    "weights": "/train/clip.pt",
                    "vocab": "/train/v.txt.gz",
                }
            },
            "state_dict": {"w": torch.ones(2)},
        },
        files / "transformer.ckpt",
    )
    for name in ("tokenizer.ckpt", "text_weights.pt", "text_vocab.txt.gz"):
        (files / name).write_bytes(b"x")
    scratch = tmp_path / "tmpdir"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    loaded = []
    monkeypatch.setattr(
        TextToMotion,
        "from_files",
        classmethod(
            lambda cls, *args, **kwargs: (
                loaded.append((args, kwargs)) or SimpleNamespace(part_aware=False, precision="fp32")
            )
        ),
    )
    context = SimpleNamespace(
        model_config={},
        artifacts={
            "transformer": str(files / "transformer.ckpt"),
            "tokenizer": str(files / "tokenizer.ckpt"),
            "text_weights": str(files / "text_weights.pt"),
            "text_vocab": str(files / "text_vocab.txt.gz"),
        },
    )
    TextToMotionPyfunc().load_context(context)
    assert loaded  # the model was built ...
    assert list(scratch.iterdir()) == []  # ... and no temporary folder outlives load_context
    assert sorted(p.name for p in files.iterdir()) == [
        "text_vocab.txt.gz",
        "text_weights.pt",
        "tokenizer.ckpt",
        "transformer.ckpt",
    ]

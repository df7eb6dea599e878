"""Bad input, end to end: every refusal of issue 13 and of the README through the real `mmm`
command (a process each), which must exit 2 with a one-line message naming the input, print no
traceback, leave no output folder and change nothing in the MLflow store; plus the shared range
checks behind it (SamplingConfig, the served bundle's params) and the caption reader/renderer.

Each process is forked from a server that has imported the libraries once (tests/helpers/forked.py):
starting Python and torch anew costs 2-10 s a command on a small machine. The commands of a table run
a few at a time (a module fixture), and each case then checks its own result."""

import hashlib
import math
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import D, write_dataset
from tests.helpers.forked import ForkedCLI

ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "PYTHONWARNINGS": "ignore"}
WORKERS = 3


def tree(folder: Path) -> dict[str, str]:
    """Every file under `folder` with the sha256 of its content (folders as '<dir>')."""
    out = {}
    for path in sorted(folder.rglob("*")):
        rel = str(path.relative_to(folder))
        out[rel] = "<dir>" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def assert_refused(result: subprocess.CompletedProcess, expected: list[str]) -> None:
    """Exit 2, no traceback, exactly one error line, naming every string of `expected`."""
    err = result.stderr
    assert result.returncode == 2, (
        f"exit {result.returncode}\nstdout: {result.stdout[-2000:]}\nstderr: {err[-4000:]}"
    )
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, err
    assert err.rstrip().endswith(errors[0]), f"the message is not one line:\n{err}"
    for text in expected:
        assert text in errors[0], f"{text!r} not in {errors[0]!r}"


# -- inputs refused before any model is loaded -----------------------------------------------------
GEN = ["generate", "--text", "a person walks forward", "--out", "{out}"]
LONG = ["generate-long", "--text", "a person walks", "--text", "a person jumps", "--out", "{out}"]
OUTPAINT = ["edit", "outpaint", "--source", "{source}", "--keep", "0:40", "--out", "{out}"]

BEFORE_MODEL = {
    # sampling settings: NaN, infinite, out of range (issue 13)
    "temperature nan": (GEN + ["--temperature", "nan"], ["--temperature nan", "0.001 to 100"]),
    "temperature inf": (GEN + ["--temperature", "inf"], ["--temperature inf", "0.001 to 100"]),
    "temperature negative": (
        GEN + ["--temperature", "-1"],
        ["--temperature -1.0", "0 (always the most likely code)"],
    ),
    "guidance nan": (GEN + ["--guidance", "nan"], ["--guidance nan", "from 0 to 100"]),
    "guidance inf": (GEN + ["--guidance", "inf"], ["--guidance inf", "from 0 to 100"]),
    "guidance negative": (GEN + ["--guidance", "-2"], ["--guidance -2.0", "from 0 to 100"]),
    "top-k nan": (GEN + ["--top-k", "nan"], ["--top-k nan", "(0, 1]"]),
    "top-k above 1": (GEN + ["--top-k", "1.5"], ["--top-k 1.5", "(0, 1]"]),
    "top-p nan": (GEN + ["--top-p", "nan"], ["--top-p nan", "(0, 1]"]),
    "top-p inf": (GEN + ["--top-p", "inf"], ["--top-p inf", "(0, 1]"]),
    "iterations above 100": (GEN + ["--iterations", "101"], ["--iterations 101", "from 1 to 100"]),
    "iterations zero": (GEN + ["--iterations", "0"], ["--iterations 0", "from 1 to 100"]),
    "num-samples zero": (GEN + ["--num-samples", "0"], ["--num-samples 0", "from 1 to 64"]),
    "num-samples above bound": (GEN + ["--num-samples", "65"], ["--num-samples 65", "from 1 to 64"]),
    "prompts x num-samples above bound": (
        GEN + ["--text", "a person jumps"] * 16 + ["--num-samples", "4"],
        ["17 prompts x --num-samples 4 is 68 samples", "at most 64 per call"],
    ),
    "candidates zero": (GEN + ["--candidates", "0"], ["--candidates 0", "1 to 16"]),
    "candidates above bound": (GEN + ["--candidates", "17"], ["--candidates 17", "1 to 16"]),
    "seed negative": (GEN + ["--seed", "-1"], ["--seed -1", "0 to 2^63-1"]),
    "seed 2^63": (GEN + ["--seed", str(2**63)], [f"--seed {2**63}", "0 to 2^63-1"]),
    "long seed 2^64": (LONG + ["--seed", str(2**64)], [f"--seed {2**64}", "0 to 2^63-1"]),
    "long candidates zero": (LONG + ["--candidates", "0"], ["--candidates 0", "1 to 16"]),
    "released decoding with top-k": (
        GEN + ["--decoding", "released", "--top-k", "0.5"],
        ["released decoding", "top_k=0.5"],
    ),
    # placement and counts of edits and long sequences
    "place negative": (OUTPAINT + ["--place", "-4"], ["--place -4", "0 or more"]),
    "edit num-samples above bound": (
        OUTPAINT + ["--num-samples", "100"],
        ["--num-samples 100", "from 1 to 64"],
    ),
    "transition codes negative": (
        LONG + ["--transition-codes", "-1"],
        ["--transition-codes -1", "0 or more"],
    ),
    "lengths not numbers": (LONG + ["--lengths", "80,abc"], ["--lengths '80,abc'"]),
    # empty text and paragraphs (README: empty text; issue 13: empty or whitespace-only paragraph)
    "empty text": (["generate", "--text", "", "--out", "{out}"], ["--text is empty"]),
    "whitespace text": (["generate", "--text", "   ", "--out", "{out}"], ["--text is empty"]),
    "whitespace paragraph": (
        ["generate-long", "--paragraph", " \t ", "--out", "{out}"],
        ["--paragraph is empty"],
    ),
    "empty paragraph": (["generate-long", "--paragraph", "", "--out", "{out}"], ["--paragraph is empty"]),
    "paragraph without action": (
        ["generate-long", "--paragraph", " , . ; ", "--out", "{out}"],
        ["no action found in the paragraph"],
    ),
    "one empty segment": (
        ["generate-long", "--text", "a person walks", "--text", " ", "--out", "{out}"],
        ["--text is empty"],
    ),
    "edit with empty text": (OUTPAINT + ["--text", "  "], ["--text is empty"]),
    "edit candidates without text": (
        OUTPAINT + ["--candidates", "4"],
        ["--candidates", "judges the edited frames against --text"],
    ),
    "edit candidates above bound": (
        OUTPAINT + ["--text", "a person jumps", "--candidates", "17"],
        ["--candidates 17", "1 to 16"],
    ),
    # README: a source of the wrong shape
    "source wrong shape": (
        ["edit", "inbetween", "--source", "{bad_shape}", "--keep", "0:40,60:80", "--out", "{out}"],
        ["bad_shape.npy", "expected features (T, 263)"],
    ),
    "source with NaN": (
        ["edit", "complete", "--source", "{nan_source}", "--keep", "0:40", "--out", "{out}"],
        ["nan_source.npy", "NaN/Inf"],
    ),
    # other commands' bounds
    "synth seed negative": (
        ["data", "synth", "--out", "{out}", "--seed", "-5", "--num-clips", "2"],
        ["--seed -5", "0 to 2^63-1"],
    ),
    "synth extra clips negative": (
        ["data", "synth", "--out", "{out}", "--num-clips", "2", "--extra-train-clips", "-3"],
        ["--extra-train-clips -3", "0 or more"],
    ),
    "synth workers zero": (
        ["data", "synth", "--out", "{out}", "--num-clips", "2", "--workers", "0"],
        ["--workers 0", "1 or more"],
    ),
    "synth composite fraction above one": (
        ["data", "synth", "--out", "{out}", "--num-clips", "2", "--extra-composite-fraction", "1.5"],
        ["--extra-composite-fraction 1.5", "between 0 and 1"],
    ),
    "preview count zero": (["data", "preview", "{dataset}", "--out", "{out}", "--count", "0"], ["--count 0"]),
    "render fps nan": (["render", "{joints}", "--out", "{out}/x.gif", "--fps", "nan"], ["--fps nan"]),
    "render fps zero": (["render", "{joints}", "--out", "{out}/x.gif", "--fps", "0"], ["--fps 0.0"]),
    # issue 13: a caption span #0#inf (HumanML3D caption line): the file and line are named
    "caption span inf (check)": (
        ["data", "check", "{inf_caption}", "--on-invalid", "error"],
        ["texts/000000.txt:2", "0..inf s is not finite"],
    ),
    "caption span inf (preview)": (
        ["data", "preview", "{inf_caption}", "--out", "{out}"],
        ["texts/000000.txt:2", "0..inf s is not finite"],
    ),
    # README: bad data names the file (malformed caption line, a split naming a missing id), a
    # misspelt config key names the valid ones, the released upper-body pair is refused
    "malformed caption line": (
        ["data", "check", "{malformed}", "--on-invalid", "error"],
        ["texts/000000.txt:1", "malformed caption line"],
    ),
    "split names a missing id": (["data", "check", "{missing_id}", "--on-invalid", "error"], ["000099"]),
    "misspelt config key": (["train", "stage1", "trainer.max_stepz=5"], ["max_stepz"]),
    "feat bias zero": (
        ["data", "stats", "{dataset}", "--evaluator-style", "--feat-bias", "0", "--write"],
        ["--feat-bias 0 is not allowed", "above 0"],
    ),
    "convert output is a folder": (
        ["convert", "features-to-joints", "{source}", "{dataset}"],
        ["dataset is a folder", "motion.npy"],
    ),
    "convert output under a file": (
        ["convert", "features-to-joints", "{source}", "{source}/joints.npy"],
        ["source.npy is a file, not a folder"],
    ),
    "evaluate with no replications": (["evaluate", "protocol.replications=0"], ["protocol.replications=0"]),
    "ablation with an empty grid": (["ablate", "temperature", "grids.temperature=[]"], ["grid is empty"]),
    "ablation of a negative reset": (["ablate", "reset", "grids.reset=[20,-5]"], ["grids.reset=[-5]"]),
    "ablation of top-k 0": (["ablate", "topk", "grids.topk=[0.5,0]"], ["top_k", "(0, 1]"]),
    "ablation training override misspelt": (
        ["ablate", "cross-layers", "stage2_overrides=[trainer.max_stepz=3]"],
        ["setting '0 cross-attention layers'", "stage2 training", "max_stepz", "Did you mean: 'max_steps'"],
    ),
    "ablation of more cross layers than layers": (
        ["ablate", "cross-layers", "grids.cross_layers=[0,9]"],
        ["setting '9 cross-attention layers'", "num_cross_layers=9", "num_layers=4"],
    ),
    "no training steps": (["train", "stage1", "trainer.max_steps=0"], ["trainer.max_steps=0", "at least 1"]),
    "fit ends before its first validation": (
        ["train", "stage1", "trainer.max_steps=5", "refine.steps=0"],
        ["the fit's 5 steps end before its first validation", "trainer.val_check_interval=100"],
    ),
    "window not a multiple of the unit": (
        ["train", "evaluator", "data.window=30"],
        ["data.window=30", "data.unit_length=4", "data.window=28"],
    ),
    "empty promotion criteria": (["promote", "tokenizer", "criteria.tokenizer=[]"], ["is empty"]),
    "negative promotion samples": (["promote", "text2motion", "samples=-1"], ["samples=-1", "0 for none"]),
    # a later step's overrides are checked before the first step trains (it used to train the
    # evaluator and the tokenizer, minutes, before refusing a misspelt stage-2 key)
    "pipeline step override misspelt": (
        ["pipeline", "full", "overrides.stage2=[trainer.max_stepz=3]"],
        ["overrides.stage2", "max_stepz"],
    ),
    "negative refinement": (["train", "stage1", "refine.steps=-1"], ["refine.steps=-1", "0 or more"]),
    # a store that is not there is never created by a command that only reads, and a file that is
    # not one is named
    "generate with no store here": (GEN + ["--length", "60"], ["no text-to-motion model to use"]),
    "models list with no store here": (["models", "list"], ["no MLflow store at"]),
    "promote with no store here": (["promote", "tokenizer", "candidate=deadbeef"], ["no MLflow store at"]),
    "dashboard on a mistyped store": (
        ["dashboard", "--tracking-uri", "sqlite:///{out}/typo/mlflow.db"],
        ["no MLflow store at", "typo/mlflow.db"],
    ),
    "tracking uri not a database": (
        GEN + ["--length", "60", "--tracking-uri", "sqlite:///{source}"],
        ["source.npy is not an SQLite database"],
    ),
    "released upper-body import": (
        ["import", "released-upperbody", "--vq", "{source}", "--stats", "{dataset}"],
        ["the released upper-body pair cannot be mapped"],
    ),
    # a device this machine does not have (cuda:7: refused with or without a GPU here), or no device
    "generate on a GPU not here": (GEN + ["--device", "cuda:7"], ["--device='cuda:7'"]),
    "generate on no device": (GEN + ["--device", "banana"], ["--device='banana' is not a device"]),
    "evaluate on a GPU not here": (["evaluate", "device=cuda:7"], ["device='cuda:7'"]),
    # nothing replaced unasked; no motion that is not numbers; no render too large for memory
    "convert over an existing file": (
        ["convert", "features-to-joints", "{source}", "{existing_npy}"],
        ["existing.npy already exists", "--overwrite"],
    ),
    "convert of true/false values": (
        ["convert", "features-to-joints", "{mask}", "{out}.npy"],
        ["mask.npy", "bool values"],
    ),
    "render over an existing file": (
        ["render", "{joints}", "--out", "{existing_gif}"],
        ["existing.gif already exists", "--overwrite"],
    ),
    "render too long to hold": (
        ["render", "{long_joints}", "--out", "{out}.gif"],
        ["long_joints.npy: 6001 frames x 1 motion(s)", "6000 panel frames"],
    ),
    "export over existing files": (
        ["export", "released", "--model", "{source}", "--out", "{exported}"],
        ["trans.pth already exists", "--overwrite"],
    ),
    "dashboard port 0": (["dashboard", "--port", "0"], ["--port 0", "1 to 65535"]),
    "a folder as the store": (
        ["models", "list", "--tracking-uri", "{dataset}"],
        ["--tracking-uri", "dataset: not an MLflow store", "sqlite:///path/to/mlflow.db"],
    ),
    "data check min-length at the limit": (
        ["data", "check", "{dataset}", "--min-length", "200"],
        ["--min-length 200", "below the length limit 200"],
    ),
    "overlapping kept ranges": (
        ["edit", "inbetween", "--source", "{source}", "--keep", "0:100,50:170", "--out", "{out}"],
        ["--keep ranges 0:100 and 50:170 overlap"],
    ),
    "data check min-length 0": (
        ["data", "check", "{dataset}", "--min-length", "0"],
        ["--min-length 0", "1 or more"],
    ),
    "crop shorter than a code": (
        ["train", "stage1", "data.max_length=0"],
        ["data.max_length=0", "at least 4"],
    ),
    "text always dropped": (
        ["train", "stage2", "corruption.cond_drop=1"],
        ["corruption.cond_drop", "[0, 1)"],
    ),
    "final share of a whole run": (
        ["train", "stage2", "optim.final_share=1"],
        ["optim.final_share=1.0", "[0, 1)", "optim.final_share=0.25"],
    ),
    "weights averaged with decay 1": (
        ["train", "stage2", "callbacks.weight_ema=1"],
        ["callbacks.weight_ema=1.0", "[0, 1)", "callbacks.weight_ema=0.99"],
    ),
    "unknown token encoding": (
        ["train", "stage2", "token_encoding=search"],
        ["token_encoding='search'", "tokenizer, nearest"],
    ),
}


def _inputs(folder: Path) -> dict[str, str]:
    """The input files the table refers to, written under `folder` (outside every case's cwd)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    np.save(folder / "source.npy", rng.normal(size=(80, D)).astype(np.float32))
    np.save(folder / "bad_shape.npy", np.zeros((80, 5), np.float32))
    nan_source = rng.normal(size=(80, D)).astype(np.float32)
    nan_source[3, 7] = np.nan
    np.save(folder / "nan_source.npy", nan_source)
    joints = rng.normal(size=(20, 22, 3)).astype(np.float32)
    np.save(folder / "joints.npy", joints)
    np.save(folder / "long_joints.npy", np.tile(joints, (301, 1, 1))[:6001])
    np.save(folder / "mask.npy", np.ones((80, D), bool))
    np.save(folder / "existing.npy", np.zeros(3, np.float32))
    (folder / "existing.gif").write_bytes(b"GIF89a")
    (folder / "exported").mkdir()
    (folder / "exported" / "trans.pth").write_bytes(b"kept")
    good_line = "a person walks#a/DET person/NOUN walk/VERB#0.0#0.0"
    inf_caption = folder / "inf_caption"
    write_dataset(
        inf_caption,
        {"000000": (60, [good_line, "a person jumps#a/DET person/NOUN jump/VERB#0#inf"])},
        {s: ["000000"] for s in ("train", "val", "test")},
    )
    (inf_caption / "new_joints").mkdir()
    np.save(inf_caption / "new_joints" / "000000.npy", rng.normal(size=(60, 22, 3)).astype(np.float32))
    dataset = folder / "dataset"
    write_dataset(dataset, {"000000": (60, [good_line])}, {s: ["000000"] for s in ("train", "val", "test")})
    write_dataset(
        folder / "malformed",
        {"000000": (60, ["a person walks#0.0"])},
        {s: ["000000"] for s in ("train", "val", "test")},
    )
    write_dataset(
        folder / "missing_id",
        {"000000": (60, [good_line])},
        {s: ["000000", "000099"] for s in ("train", "val", "test")},
    )
    return {
        "malformed": str(folder / "malformed"),
        "missing_id": str(folder / "missing_id"),
        "source": str(folder / "source.npy"),
        "bad_shape": str(folder / "bad_shape.npy"),
        "nan_source": str(folder / "nan_source.npy"),
        "joints": str(folder / "joints.npy"),
        "long_joints": str(folder / "long_joints.npy"),
        "mask": str(folder / "mask.npy"),
        "existing_npy": str(folder / "existing.npy"),
        "existing_gif": str(folder / "existing.gif"),
        "exported": str(folder / "exported"),
        "inf_caption": str(inf_caption),
        "dataset": str(dataset),
    }


def _run_table(table: dict, files: dict[str, str], base: Path, extra: list[str] = ()) -> dict:
    """Run every case in its own empty cwd; returns name -> (result, cwd, tree before, tree after)."""

    def one(item):
        name, (args, _) = item
        cwd = base / name.replace(" ", "_")
        cwd.mkdir(parents=True)
        before = tree(cwd)
        argv = [a.format(out=cwd / "out" / "sample", **files) for a in args] + list(extra)
        # Relative defaults such as sqlite:///mlflow.db and outputs/ would land in `cwd`, where the
        # tests look for them.
        result = cli.run(argv, cwd, ENV)
        return name, (result, cwd, before, tree(cwd))

    with ForkedCLI(WORKERS) as cli, ThreadPoolExecutor(WORKERS) as pool:
        return dict(pool.map(one, table.items()))


@pytest.fixture(scope="module")
def before_model_results(tmp_path_factory):
    base = tmp_path_factory.mktemp("bad-input")
    files = _inputs(base / "inputs")
    inputs_before = tree(base / "inputs")
    started = time.perf_counter()
    results = _run_table(BEFORE_MODEL, files, base / "cases")
    print(f"[bad input] {len(results)} commands in {time.perf_counter() - started:.1f} s")
    return {"cases": results, "inputs": (inputs_before, tree(base / "inputs"))}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(BEFORE_MODEL))
def test_refused_before_any_model_loads(before_model_results, name):
    result, cwd, before, after = before_model_results["cases"][name]
    assert_refused(result, BEFORE_MODEL[name][1])
    # No output folder, no MLflow store, no cache: the case's folder is exactly as it was (empty).
    assert after == before == {}


@pytest.mark.slow
def test_refusals_leave_the_input_files_as_they_were(before_model_results):
    """The files named as outputs that already existed (existing.npy, existing.gif, exported/)
    and every input are byte for byte as written (hidden caches the data commands keep beside a
    dataset, such as .captions-pack/, aside)."""

    def visible(files: dict[str, str]) -> dict[str, str]:
        return {k: v for k, v in files.items() if not any(part.startswith(".") for part in Path(k).parts)}

    before, after = (visible(files) for files in before_model_results["inputs"])
    assert after == before and "exported/trans.pth" in after


# -- inputs refused once the model is known (lengths depend on it; README) ------------------------
WITH_MODEL = {
    "length below 40": (
        ["generate", "--model", "{model}", "--text", "a person walks", "--length", "30", "--out", "{out}"],
        ["--length 30 frames is outside 40..196"],
    ),
    "length above 196": (
        ["generate", "--model", "{model}", "--text", "a person walks", "--length", "500", "--out", "{out}"],
        ["--length 500 frames is outside 40..196"],
    ),
    "segment length below 40": (
        [
            "generate-long",
            "--model",
            "{model}",
            "--text",
            "a person walks",
            "--text",
            "a person jumps",
            "--lengths",
            "80,20",
            "--out",
            "{out}",
        ],
        ["segment length 20 frames is outside 40..196"],
    ),
    "unknown model": (
        [
            "generate",
            "--model",
            "models:/no-such-model@champion",
            "--text",
            "a person walks",
            "--length",
            "80",
            "--out",
            "{out}",
        ],
        ["no-such-model"],
    ),
    "edit source of 3 frames": (
        [
            "edit",
            "complete",
            "--model",
            "{model}",
            "--source",
            "{short_source}",
            "--keep",
            "0:3",
            "--length",
            "80",
            "--out",
            "{out}",
        ],
        ["short_source.npy: 3 frames", "at least 4"],
    ),
    "edit source of another skeleton": (
        [
            "edit",
            "complete",
            "--model",
            "{model}",
            "--source",
            "{kit_joints}",
            "--keep",
            "0:40",
            "--out",
            "{out}",
        ],
        ["kit_joints.npy: joints (60, 21, 3), read as features (59, 251), but the model reads 263-d"],
    ),
}


@pytest.fixture(scope="module")
def with_model_results(trained, tmp_path_factory):
    base = tmp_path_factory.mktemp("bad-input-model")
    store = Path(trained["uri"].removeprefix("sqlite:///"))
    digest = hashlib.sha256(store.read_bytes()).hexdigest()
    short_source = base / "inputs" / "short_source.npy"
    short_source.parent.mkdir()
    np.save(short_source, np.random.default_rng(0).normal(size=(3, D)).astype(np.float32))
    kit_joints = base / "inputs" / "kit_joints.npy"  # a KIT-ML skeleton for a HumanML3D model
    np.save(kit_joints, np.random.default_rng(1).normal(size=(60, 21, 3)).astype(np.float32))
    started = time.perf_counter()
    results = _run_table(
        WITH_MODEL,
        {
            "model": str(trained["checkpoint"]),
            "short_source": str(short_source),
            "kit_joints": str(kit_joints),
        },
        base / "cases",
        extra=["--tracking-uri", trained["uri"]],
    )
    print(f"[bad input] {len(results)} commands with a model in {time.perf_counter() - started:.1f} s")
    return results, digest, store


@pytest.mark.slow
@pytest.mark.parametrize("name", list(WITH_MODEL))
def test_refused_once_the_model_is_known(with_model_results, name):
    results, digest, store = with_model_results
    result, cwd, before, after = results[name]
    assert_refused(result, WITH_MODEL[name][1])
    # No output folder; what loading the model put in the download cache (outputs/cache/) may stay.
    assert before == {} and not (cwd / "out").exists()
    assert all(path.startswith("outputs") for path in after) and all(
        path.startswith("outputs/cache/") for path in after if path.count("/") > 1
    )
    assert hashlib.sha256(store.read_bytes()).hexdigest() == digest, "the MLflow store changed"


@pytest.mark.slow
def test_console_script_refuses_like_the_module(tmp_path):
    """The installed `mmm` entry point itself (not only `python -m mmm.cli`)."""
    script = Path(sys.executable).with_name("mmm")
    if not script.exists():
        pytest.skip("no console script next to this interpreter")
    result = subprocess.run(
        [
            str(script),
            "generate",
            "--text",
            "a person walks",
            "--temperature",
            "nan",
            "--out",
            str(tmp_path / "out"),
        ],
        cwd=tmp_path,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert_refused(result, ["--temperature nan"])
    assert list(tmp_path.iterdir()) == []


# -- the one place the ranges live ------------------------------------------------------------------
@pytest.mark.parametrize(
    "field, value, allowed",
    [
        ("temperature", math.nan, "0.001 to 100"),
        ("temperature", math.inf, "0.001 to 100"),
        ("temperature", -0.5, "0.001 to 100"),
        ("temperature", 1e-9, "0.001 to 100"),
        ("guidance_scale", math.nan, "0 to 100"),
        ("guidance_scale", -math.inf, "0 to 100"),
        ("guidance_scale", 1e9, "0 to 100"),
        ("top_k", math.nan, "(0, 1]"),
        ("top_k", 0.0, "(0, 1]"),
        ("top_p", math.inf, "(0, 1]"),
        ("top_p", -0.1, "(0, 1]"),
        ("max_iterations", 101, "1 to 100"),
        ("max_iterations", 0, "1 to 100"),
        ("max_iterations", 2.5, "1 to 100"),
        ("max_iterations", True, "1 to 100"),
    ],
)
def test_sampling_config_names_field_value_and_range(field, value, allowed):
    from mmm.generation.settings import SamplingConfig, SamplingValueError

    with pytest.raises(SamplingValueError) as err:
        SamplingConfig(**{field: value})
    assert err.value.field == field and err.value.value is value
    assert str(err.value).startswith(f"{field} {value!r} is not allowed") and allowed in str(err.value)


def test_sampling_config_accepts_the_edges():
    from mmm.generation.settings import MAX_ITERATIONS, SamplingConfig, check_count, check_seed

    SamplingConfig(
        max_iterations=MAX_ITERATIONS, temperature=100.0, guidance_scale=100.0, top_k=1.0, top_p=1.0
    )
    SamplingConfig(max_iterations=1, temperature=0.0, guidance_scale=0.0)
    SamplingConfig(temperature=0.001)
    assert (
        check_seed(2**63 - 1) == 2**63 - 1
        and check_seed(np.int64(3)) == 3
        and check_count(64, "num_samples") == 64
    )


@pytest.mark.parametrize(
    "params, message",
    [
        ({"temperature": math.nan}, "params: temperature nan is not allowed"),
        ({"temperature": -1.0}, "params: temperature -1.0 is not allowed"),
        ({"guidance_scale": math.inf}, "params: guidance_scale inf is not allowed"),
        ({"top_k": 0.0}, "params: top_k 0.0 is not allowed"),
        ({"top_p": math.nan}, "params: top_p nan is not allowed"),
        ({"max_iterations": 101}, "params: max_iterations 101 is not allowed: an integer from 1 to 100"),
        ({"max_iterations": 2.5}, "params: max_iterations 2.5 is not allowed"),
        ({"temperature": "hot"}, "params: temperature 'hot' is not a number"),
    ],
)
def test_bundle_params_use_the_same_ranges(params, message):
    """The served bundle's params go through SamplingConfig too: HTTP 400, the CLI's ranges."""
    from mlflow.exceptions import MlflowException

    from mmm.registry.bundle import sampling_config

    with pytest.raises(MlflowException) as err:
        sampling_config(params)
    assert message in str(err.value) and err.value.get_http_status_code() == 400


# -- captions ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("span", ["0#inf", "inf#inf", "-inf#2.0", "1.0#Infinity"])
def test_an_infinite_caption_span_names_file_and_line(span):
    from mmm.data.humanml3d import DataError, parse_caption_line

    with pytest.raises(
        DataError, match=r"^texts/1\.txt:4: caption span .* s is not finite; write the span in seconds"
    ):
        parse_caption_line(f"a man jumps#a/DET man/NOUN jump/VERB#{span}", "texts/1.txt", 4)


@pytest.mark.timeout(60)  # the character-by-character wrap this replaces took minutes
def test_a_20000_character_word_wraps_fast():
    from mmm.render.stick import _header_lines, _Style, _wrap

    style = _Style.for_size(320, 320)
    word = "w" * 20_000
    started = time.perf_counter()
    lines = _header_lines([f"a person {word} walks"], style)[0]
    seconds = time.perf_counter() - started
    assert seconds < 1.0, f"wrapping took {seconds:.2f} s"
    assert len(lines) == 3 and lines[0] == "a person" and lines[-1].endswith("…")
    assert all(style.font.getlength(line) <= 320 - 8 for line in lines)
    assert set("".join(lines[1:])[:-1]) == {"w"}
    # A word a little too wide is cut by characters, and the rest follows on the next lines.
    short = _wrap("ab " + "x" * 60 + " cd", style.font, 100, max_lines=10)
    assert short[0] == "ab" and len(short) >= 3
    assert "".join(short).replace(" ", "") == "ab" + "x" * 60 + "cd"
    assert all(style.font.getlength(line) <= 100 for line in short)


@pytest.mark.timeout(60)
def test_a_20000_character_caption_renders_fast(tmp_path):
    from mmm.render.stick import render_gif

    joints = np.random.default_rng(0).normal(size=(4, 22, 3)).astype(np.float32)
    started = time.perf_counter()
    render_gif([joints], tmp_path / "long.gif", captions=["x" * 20_000])
    seconds = time.perf_counter() - started
    assert seconds < 1.0 and (tmp_path / "long.gif").stat().st_size > 0, f"rendering took {seconds:.2f} s"

"""The text-to-motion bundle: logged, registered with an alias, loaded as a pyfunc, read back as
checkpoints, and served by `mlflow models serve` as a real process on loopback."""

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

NAME = "mmm-test-bundle"  # not mmm-text2motion: other tests read that name's champion
TIMINGS: dict[str, float] = {}


def _report(key: str, seconds: float) -> None:
    TIMINGS[key] = seconds
    print(f"[serving] {key}: {seconds:.2f} s")


@pytest.fixture(scope="module")
def store(trained):
    """The fixture's sqlite store as the process-wide MLflow store for this module, restored after."""
    import mlflow
    from mlflow.tracking._tracking_service import utils

    previous, env = utils._tracking_uri, os.environ.get("MLFLOW_TRACKING_URI")
    mlflow.set_tracking_uri(trained["uri"])
    try:
        yield trained["uri"]
    finally:
        mlflow.set_tracking_uri(previous)
        if env is not None:
            os.environ["MLFLOW_TRACKING_URI"] = env


@pytest.fixture(scope="module")
def registered(trained, store, tmp_path_factory):
    """A bundle logged from copies of the fixture's checkpoints (deleted right after logging, so
    nothing can refer to them), registered as NAME with alias champion."""
    import mlflow
    from mlflow import MlflowClient

    from mmm.registry.bundle import log_bundle

    stage1 = torch.load(trained["checkpoint"], map_location="cpu", weights_only=True)["hyper_parameters"][
        "stage1"
    ]["checkpoint"]
    staging = tmp_path_factory.mktemp("bundle-src")
    stage2_copy, stage1_copy = staging / "s2.ckpt", staging / "s1.ckpt"
    shutil.copyfile(trained["checkpoint"], stage2_copy)
    shutil.copyfile(stage1, stage1_copy)
    client = MlflowClient(store)
    experiment = client.create_experiment(
        "mmm-bundle-test", artifact_location=(Path(trained["out"]) / "bundle-art").as_uri()
    )
    t0 = time.perf_counter()
    with mlflow.start_run(experiment_id=experiment) as run:
        info = log_bundle(stage2_copy, stage1_copy, registered_model_name=NAME, tags={"purpose": "test"})
    _report("log_bundle (incl. registration)", time.perf_counter() - t0)
    shutil.rmtree(staging)
    client.set_registered_model_alias(NAME, "champion", str(info.registered_model_version))
    return {
        "info": info,
        "run_id": run.info.run_id,
        "stage2": trained["checkpoint"],
        "stage1": stage1,
        "uri": f"models:/{NAME}@champion",
    }


@pytest.fixture(scope="module")
def served_model(registered):
    import mlflow

    t0 = time.perf_counter()
    model = mlflow.pyfunc.load_model(registered["uri"])
    _report("pyfunc.load_model (download + load_context)", time.perf_counter() - t0)
    return model


@pytest.mark.slow
def test_registered_bundle_records_identity_and_requirements(registered, store):
    from mlflow import MlflowClient
    from mlflow.models import Model

    from mmm.generation.model import TextToMotion

    expected = TextToMotion.from_files(registered["stage2"], registered["stage1"]).identity
    client = MlflowClient(store)
    version = client.get_model_version_by_alias(NAME, "champion")
    assert str(version.version) == str(registered["info"].registered_model_version)
    assert version.tags["mmm.text_encoder"] == expected["text_encoder"]
    assert version.tags["mmm.stage1.identity"] == expected["stage1"]["identity"]
    assert version.tags["purpose"] == "test"
    logged = client.get_logged_model(registered["info"].model_id)
    assert (
        logged.source_run_id == registered["run_id"]
        and logged.tags["mmm.text_encoder"] == expected["text_encoder"]
    )
    meta = Model.load(registered["uri"]).metadata["mmm"]
    assert (
        meta["text_encoder"] == expected["text_encoder"]
        and meta["max_frames"] == 196
        and meta["default_length"] == 120
    )
    import mlflow

    reqs = (
        Path(mlflow.artifacts.download_artifacts(f"{registered['uri']}/requirements.txt")).read_text().split()
    )
    assert any(r.startswith("mmm-motion[text]==") for r in reqs) and f"mlflow=={mlflow.__version__}" in reqs
    assert any(r.startswith("torch==") and "+" not in r for r in reqs)


@pytest.mark.slow
def test_pyfunc_generates_requested_lengths_deterministically(served_model):
    texts = ["a person walks forward", "a person turns around"]
    t0 = time.perf_counter()
    out = served_model.predict(pd.DataFrame({"text": texts, "length": [80, 83]}))
    _report("pyfunc.predict 2 rows (80, 83 frames)", time.perf_counter() - t0)
    assert [o["text"] for o in out] == texts and [o["length"] for o in out] == [80, 83]
    joints = [np.asarray(o["joints"]) for o in out]
    assert [j.shape for j in joints] == [(80, 22, 3), (83, 22, 3)]
    assert [np.asarray(o["features"]).shape for o in out] == [(80, 263), (83, 263)]
    assert all(np.isfinite(j).all() for j in joints)
    json.dumps(out)  # what the scoring server sends

    again = served_model.predict(pd.DataFrame({"text": texts, "length": [80, 83], "seed": [0, 0]}))
    assert all(np.array_equal(np.asarray(a["joints"]), b) for a, b in zip(again, joints))
    # A row's motion does not depend on the other rows of the request.
    alone = served_model.predict(pd.DataFrame({"text": texts[1:], "length": [83]}))
    assert np.array_equal(np.asarray(alone[0]["joints"]), joints[1])
    other = served_model.predict(pd.DataFrame({"text": texts[:1], "length": [80], "seed": [7]}))
    assert not np.array_equal(np.asarray(other[0]["joints"]), joints[0])
    # Missing length: the documented default.
    default = served_model.predict(pd.DataFrame({"text": ["a person jumps"]}))
    assert np.asarray(default[0]["joints"]).shape == (120, 22, 3)


@pytest.mark.slow
def test_raw_input_forms_and_params(served_model):
    model = served_model.unwrap_python_model()
    records = model.predict(
        None, [{"text": "a person walks forward", "length": 40}, {"text": "a person sits", "length": None}]
    )
    columns = model.predict(
        None, {"text": ["a person walks forward", "a person sits"], "length": [40, float("nan")]}
    )
    assert [o["length"] for o in records] == [40, 120] == [o["length"] for o in columns]
    assert np.array_equal(np.asarray(records[0]["joints"]), np.asarray(columns[0]["joints"]))
    scalar = model.predict(None, {"text": "a person walks forward", "length": 40})
    assert np.array_equal(np.asarray(scalar[0]["joints"]), np.asarray(records[0]["joints"]))
    greedy = served_model.predict(
        pd.DataFrame({"text": ["a person walks forward"], "length": [40]}),
        params={"temperature": 0.0, "max_iterations": 2},
    )
    assert np.asarray(greedy[0]["joints"]).shape == (40, 22, 3)


@pytest.mark.slow
@pytest.mark.parametrize(
    "rows, message",
    [
        ({"text": ["a person walks", "  "], "length": [80, 80]}, "row 1: text is empty"),
        ({"text": ["a person walks"], "length": [10]}, "row 0: length 10 frames is outside 40..196"),
        (
            {"text": ["a person walks", "a person runs"], "length": [80, 500]},
            "row 1: length 500 frames is outside 40..196",
        ),
        (
            {"text": ["a person walks"], "seed": [-3]},
            r"row 0: seed -3 is not allowed: an integer from 0 to 2\^63-1",
        ),
        (
            {"text": ["a person walks", "a person runs"], "seed": [1, 2**63]},
            r"row 1: seed 9223372036854775808 is not allowed: an integer from 0 to 2\^63-1",
        ),
        (
            {"text": ["a person walks", "a person runs"], "seed": [1.5, None]},
            "row 0: seed must be an integer, got 1.5",
        ),
        (  # the None makes the column float64: 2^60 + 1 arrives as 2^60
            {"text": ["a person walks", "a person runs"], "seed": [2**60 + 1, None]},
            r"row 0: seed 1152921504606846976 arrived as a float .* give every row a seed",
        ),
    ],
)
def test_bad_rows_are_refused_by_name(served_model, rows, message):
    from mlflow.exceptions import MlflowException

    with pytest.raises(ValueError, match=message) as err:
        served_model.predict(pd.DataFrame(rows))
    assert isinstance(err.value, MlflowException) and err.value.get_http_status_code() == 400


@pytest.mark.slow
def test_bad_requests_never_reach_the_model(served_model):
    from mlflow.exceptions import MlflowException

    with pytest.raises(MlflowException, match="text"):
        served_model.predict(pd.DataFrame({"length": [80]}))
    with pytest.raises(MlflowException, match="length"):
        served_model.predict(pd.DataFrame({"text": ["a person walks"], "length": [80.5]}))
    with pytest.raises(ValueError, match="row 0: length must be an integer"):
        served_model.unwrap_python_model().predict(None, [{"text": "a person walks", "length": "long"}])
    raw = served_model.unwrap_python_model()
    with pytest.raises(ValueError, match="temperature -1.0 is not allowed"):
        raw.predict(None, [{"text": "a person walks"}], params={"temperature": -1.0})
    with pytest.raises(ValueError, match=r"top_p 2.0 is not allowed: a total probability in \(0, 1\]"):
        raw.predict(None, [{"text": "a person walks"}], params={"top_p": 2.0})
    with pytest.raises(ValueError, match="max_iterations 1000 is not allowed: an integer from 1 to 100"):
        raw.predict(None, [{"text": "a person walks"}], params={"max_iterations": 1000})
    # MLflow itself drops params outside the signature with a warning; the model refuses them.
    with pytest.raises(ValueError, match="unknown params steps"):
        raw.predict(None, [{"text": "a person walks"}], params={"steps": 3})


@pytest.mark.slow
def test_rows_may_mix_given_and_absent_seed_and_length(served_model):
    """seed and length are optional per row: a request where some rows give them and others do
    not is answered, each row as if it were alone with the defaults spelled out."""
    texts = ["a person walks forward", "a person turns around", "a person jumps"]
    mixed = served_model.predict(
        pd.DataFrame({"text": texts, "length": [80, None, 44], "seed": [7, None, np.nan]})
    )
    assert [(o["length"], o["seed"]) for o in mixed] == [(80, 7), (120, 0), (44, 0)]
    for row, (text, frames, seed) in zip(mixed, zip(texts, [80, 120, 44], [7, 0, 0])):
        alone = served_model.predict(pd.DataFrame({"text": [text], "length": [frames], "seed": [seed]}))[0]
        assert np.array_equal(np.asarray(row["joints"]), np.asarray(alone["joints"]))
    records = served_model.predict([{"text": texts[0], "seed": 7, "length": 80}, {"text": texts[1]}])
    assert [(o["length"], o["seed"]) for o in records] == [(80, 7), (120, 0)]
    assert np.array_equal(np.asarray(records[0]["joints"]), np.asarray(mixed[0]["joints"]))


@pytest.mark.slow
def test_a_text_longer_than_the_encoder_reads_is_answered_with_what_was_read(served_model):
    """The text encoder reads a text's first max_words tokens (MiniLM: 256): the row says so, and
    is drawn from those tokens; a short text's row has no such key."""
    long_text = "a person walks forward and then turns around " * 60
    rows = served_model.predict(pd.DataFrame({"text": [long_text, "a person jumps"], "length": [48, 48]}))
    encoder = served_model.unwrap_python_model().model.text_encoder
    tokens = encoder.count_tokens([long_text])[0]
    assert tokens > 256 and rows[0]["text_cut"] == {"tokens": tokens, "read": 256}
    assert "text_cut" not in rows[1]


@pytest.mark.slow
def test_requests_are_bounded_in_rows(registered, served_model):
    """More rows than the bundle's max_rows (64 unless the loader's model_config says otherwise)
    are refused with HTTP 400 before anything is generated."""
    import mlflow
    from mlflow.exceptions import MlflowException

    rows = pd.DataFrame({"text": ["a person walks"] * 65, "length": [40] * 65})
    t0 = time.perf_counter()
    with pytest.raises(MlflowException, match="the request has 65 rows; at most 64 per request") as err:
        served_model.predict(rows)
    assert err.value.get_http_status_code() == 400 and time.perf_counter() - t0 < 5
    small = mlflow.pyfunc.load_model(registered["uri"], model_config={"max_rows": 2})
    with pytest.raises(MlflowException, match="the request has 3 rows; at most 2 per request"):
        small.predict(rows.head(3))
    assert [o["length"] for o in small.predict(rows.head(2))] == [40, 40]


@pytest.mark.slow
def test_bundle_checkpoints_load_as_text_to_motion(registered, served_model, store, tmp_path):
    from mmm.generation.model import TextToMotion
    from mmm.generation.sampler import SamplingConfig
    from mmm.resolve import bundle_checkpoints

    stage2, stage1, judge = bundle_checkpoints(registered["uri"], store, dst=tmp_path / "bundle")
    assert judge is None  # logged without one
    assert Path(stage2).is_relative_to(tmp_path) and Path(stage1).is_relative_to(tmp_path)
    assert Path(stage2).read_bytes() == Path(registered["stage2"]).read_bytes()
    assert Path(stage1).read_bytes() == Path(registered["stage1"]).read_bytes()
    model = TextToMotion.from_files(stage2, stage1)
    original = TextToMotion.from_files(registered["stage2"], registered["stage1"])
    for key in ("stage1", "text_encoder"):
        assert model.identity[key] == original.identity[key]
    direct = model.generate(["a person walks forward"], [80], SamplingConfig(), seed=0).joints[0]
    via_pyfunc = served_model.predict(pd.DataFrame({"text": ["a person walks forward"], "length": [80]}))[0][
        "joints"
    ]
    assert np.array_equal(direct, np.asarray(via_pyfunc, dtype=direct.dtype))

    import mlflow

    class Echo(mlflow.pyfunc.PythonModel):
        def predict(self, context, model_input, params=None):
            return model_input

    with mlflow.start_run(experiment_id=mlflow.get_experiment_by_name("mmm-bundle-test").experiment_id):
        other = mlflow.pyfunc.log_model(name="other", python_model=Echo(), pip_requirements=["mlflow"])
    with pytest.raises(ValueError, match="not a text-to-motion bundle"):
        bundle_checkpoints(other.model_uri, store, dst=tmp_path / "other")


@pytest.mark.slow
def test_log_bundle_refuses_mismatched_checkpoints(registered, tmp_path):
    import mlflow

    from mmm.fingerprint import tensors_fingerprint
    from mmm.registry.bundle import log_bundle

    with pytest.raises(RuntimeError, match="active MLflow run"):
        log_bundle(registered["stage2"], registered["stage1"])
    ckpt = torch.load(registered["stage1"], map_location="cpu", weights_only=True)
    name = next(k for k, v in ckpt["state_dict"].items() if v.is_floating_point())
    ckpt["state_dict"][name] = ckpt["state_dict"][name] + 1.0
    ckpt["weights_fingerprint"] = tensors_fingerprint(
        ckpt["state_dict"]
    )  # a retrained model: intact, other weights
    torch.save(ckpt, tmp_path / "retrained.ckpt")
    experiment = mlflow.get_experiment_by_name("mmm-bundle-test").experiment_id
    with mlflow.start_run(experiment_id=experiment) as run:
        with pytest.raises(ValueError, match="was trained on stage-1 model"):
            log_bundle(registered["stage2"], tmp_path / "retrained.ckpt")
        with pytest.raises(ValueError, match="not a stage-2"):
            log_bundle(registered["stage1"], registered["stage1"])
    assert (
        mlflow.MlflowClient()
        .search_logged_models([experiment], filter_string=f"source_run_id = '{run.info.run_id}'")
        .to_list()
        == []
    )


def test_localize_text_files_points_at_bundled_files(tmp_path):
    from mmm.resolve import localize_text_files

    ckpt = {
        "hyper_parameters": {
            "text_encoder": {
                "name": "clip-vit-b32",
                "identity": "x",
                "weights": "/train/clip.bin",
                "vocab": "/train/v.gz",
            }
        },
        "state_dict": {"w": torch.ones(2)},
    }
    torch.save(ckpt, tmp_path / "s2.ckpt")
    out = localize_text_files(
        tmp_path / "s2.ckpt", {"weights": str(tmp_path / "w.bin"), "vocab": str(tmp_path / "v.gz")}, tmp_path
    )
    text = torch.load(out, weights_only=True)["hyper_parameters"]["text_encoder"]
    assert text == {
        "name": "clip-vit-b32",
        "identity": "x",
        "weights": str(tmp_path / "w.bin"),
        "vocab": str(tmp_path / "v.gz"),
    }


# -- a real server -----------------------------------------------------------------------------
REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
SERVE_MARKER = "<!-- serve-command"


def readme_serve_block() -> tuple[list[str], dict]:
    """The README's serving instructions, as written: the shell lines of the fenced block right
    after SERVE_MARKER up to its `curl` example (backslash continuations joined), and the JSON body
    that example posts."""
    text = README.read_text()
    assert SERVE_MARKER in text, f"README.md has no {SERVE_MARKER} ...--> marker before its serving block"
    after = text[text.index(SERVE_MARKER) :]
    block = after[after.index("```bash\n") + len("```bash\n") :]
    block = block[: block.index("```")]
    lines = block.replace("\\\n", " ").splitlines()
    curl = next(i for i, line in enumerate(lines) if line.lstrip().startswith("curl "))
    body = re.search(r"-d '(.*)'", lines[curl]).group(1)
    return [line for line in lines[:curl] if line.strip()], json.loads(body)


def test_a_bundle_is_logged_as_code_and_loads_where_pickles_are_refused(registered, store, monkeypatch):
    """The pyfunc model is logged as code (mmm/registry/pyfunc_model.py), not cloudpickled: the
    bundle holds no pickle, and it loads and answers with MLflow's pickle loading switched off."""
    import importlib.util

    import mlflow
    import yaml

    local = Path(mlflow.artifacts.download_artifacts(registered["uri"]))
    assert not list(local.rglob("*.pkl")), sorted(p.name for p in local.rglob("*"))
    flavor = yaml.safe_load((local / "MLmodel").read_text())["flavors"]["python_function"]
    assert Path(flavor["model_code_path"]).name == "pyfunc_model.py" and "python_model" not in flavor
    # found, not imported: importing it would run its set_model() in this process
    code = Path(importlib.util.find_spec("mmm.registry.pyfunc_model").origin)
    assert (local / "pyfunc_model.py").read_text() == code.read_text()
    monkeypatch.setenv("MLFLOW_ALLOW_PICKLE_DESERIALIZATION", "false")
    model = mlflow.pyfunc.load_model(str(local))
    rows = model.predict(pd.DataFrame({"text": ["a person walks"], "length": [40]}))
    assert len(rows) == 1 and np.asarray(rows[0]["joints"]).shape == (40, 22, 3)


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_readme_serve_command_answers_invocations(registered, store, tmp_path):
    """The README's serve block run as written (entering the environment as it says, then its
    serve command), in a shell whose PATH lacks the environment's bin, on the test's model and a
    free port; queried with the README's request, then stopped."""
    from tests.helpers.servers import free_port, post, running

    repo = REPO
    lines, readme_request = readme_serve_block()
    assert any("make serve" in line or "mlflow models serve" in line for line in lines), lines
    venv_bins = {str(Path(sys.executable).parent), str(repo / ".venv" / "bin")}
    path = os.pathsep.join(p for p in os.environ.get("PATH", "").split(os.pathsep) if p not in venv_bins)
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "MODEL", "PORT")}
    env.update(
        PATH=path,
        MODEL=registered["uri"],
        PORT=str(port),
        MLFLOW_TRACKING_URI=store,
        MLFLOW_REGISTRY_URI=store,
        HF_HUB_OFFLINE="1",
        TRANSFORMERS_OFFLINE="1",
    )
    base = f"http://127.0.0.1:{port}"
    with running(
        ["bash", "-c", "set -e\n" + "\n".join(lines)], base, tmp_path / "server.log", repo, env
    ) as startup:
        _report("README serve command start-up (to /health 200)", startup)
        t0 = time.perf_counter()
        status, answer = post(f"{base}/invocations", readme_request)
        _report("POST /invocations, the README's request (first request)", time.perf_counter() - t0)
        assert status == 200, answer
        predictions = answer["predictions"]
        asked = readme_request["dataframe_records"]
        assert [p["text"] for p in predictions] == [r["text"] for r in asked]
        for p, r in zip(predictions, asked):
            frames = r.get("length", 120)
            assert p["length"] == frames and p["seed"] == r.get("seed", 0)
            assert np.asarray(p["joints"]).shape == (frames, 22, 3) and np.asarray(p["features"]).shape == (
                frames,
                263,
            )

        t0 = time.perf_counter()
        status, again = post(f"{base}/invocations", readme_request)
        _report("POST /invocations, same request again", time.perf_counter() - t0)
        assert status == 200 and again["predictions"][0]["joints"] == predictions[0]["joints"]

        # Rows that give a seed or a length and rows that do not, in one request.
        status, mixed = post(
            f"{base}/invocations",
            {
                "dataframe_records": [
                    {"text": "a person walks forward", "length": 80, "seed": 3},
                    {"text": "a person jumps"},
                ]
            },
        )
        assert status == 200, mixed
        assert [(p["length"], p["seed"]) for p in mixed["predictions"]] == [(80, 3), (120, 0)]

        status, error = post(
            f"{base}/invocations",
            {"dataframe_records": [{"text": "a person walks", "length": 80}, {"text": "", "length": 80}]},
        )
        assert status == 400 and "row 1: text is empty" in error["message"], error
        status, error = post(
            f"{base}/invocations", {"dataframe_records": [{"text": "a person walks", "seed": 2**63}]}
        )
        assert (
            status == 400
            and "row 0: seed 9223372036854775808 is not allowed: an integer from 0 to 2^63-1"
            in error["message"]
        ), error
        status, error = post(f"{base}/invocations", {"dataframe_records": [{"text": "a person walks"}] * 65})
        assert status == 400 and "the request has 65 rows; at most 64 per request" in error["message"], error


@pytest.mark.slow
def test_precision_param_and_model_config(served_model):
    model = served_model.unwrap_python_model()
    request = pd.DataFrame({"text": ["a person walks forward"], "length": [40], "seed": [1]})
    base = served_model.predict(request)
    assert model.model.precision == "int8"  # the CPU's default
    for precision in ("fp32", "bf16", "int8"):
        out = served_model.predict(request, params={"precision": precision})
        assert np.asarray(out[0]["joints"]).shape == (40, 22, 3)
        assert model.model.precision == precision
    served_model.predict(request, params={"precision": "fp32"})
    again = served_model.predict(request, params={"precision": ""})
    assert model.model.precision == "int8"
    assert np.array_equal(np.asarray(again[0]["joints"]), np.asarray(base[0]["joints"]))
    with pytest.raises(Exception, match="precision must be one of fp32, bf16, int8"):
        served_model.predict(request, params={"precision": "fp16"})


@pytest.fixture(scope="module")
def judged_model(trained, registered, store):
    """The same checkpoints bundled with a tiny evaluator trained on the walker data as the judge."""
    import mlflow

    from mmm.registry.bundle import log_bundle
    from tests.helpers import train_tiny_evaluator

    judge = train_tiny_evaluator(trained["walker"], trained["out"], store, output_dir="judge")
    experiment = mlflow.get_experiment_by_name("mmm-bundle-test").experiment_id
    with mlflow.start_run(experiment_id=experiment):
        info = log_bundle(
            registered["stage2"],
            registered["stage1"],
            registered_model_name=NAME + "-judged",
            judge_checkpoint=judge.best_checkpoint,
        )
    return {"model": mlflow.pyfunc.load_model(info.model_uri), "info": info, "judge": judge.best_checkpoint}


@pytest.mark.slow
def test_candidates_param_keeps_the_draw_the_bundled_judge_rates_highest(judged_model, served_model, store):
    from mlflow import MlflowClient

    from mmm.evaluation.evaluators import load_evaluator
    from mmm.generation.best_of import judge_scores
    from mmm.registry.bundle import sampling_config

    model = judged_model["model"]
    identity = load_evaluator(judged_model["judge"], store).identity
    assert model.metadata.metadata["mmm"]["judge"] == identity
    version = MlflowClient(store).get_model_version(
        NAME + "-judged", judged_model["info"].registered_model_version
    )
    assert version.tags["mmm.judge.identity"] == identity
    assert served_model.metadata.metadata["mmm"]["judge"] is None

    request = pd.DataFrame(
        {"text": ["a person walks forward", "a person jumps"], "length": [48, 40], "seed": [3, 5]}
    )
    # One candidate (the default) is the judge-less bundle's draw, with nothing added.
    plain = served_model.predict(request)
    one = model.predict(request)
    assert [sorted(o) for o in one] == [sorted(o) for o in plain] and "scores" not in one[0]
    assert all(np.array_equal(np.asarray(a["joints"]), np.asarray(b["joints"])) for a, b in zip(one, plain))

    params = {"candidates": 3, "guidance_scale": 1.5}
    best = model.predict(request, params=params)
    raw = model.unwrap_python_model()
    sampling = sampling_config({"guidance_scale": 1.5})
    for row, text, frames, seed in zip(best, request.text, request.length, request.seed):
        assert row["candidates"] == 3 and len(row["scores"]) == 3 and row["length"] == frames
        # The three draws of the row, as one batch of the model, and the judge's own cosines.
        drawn = raw.model.generate([text] * 3, [frames] * 3, sampling, seed)
        scores = judge_scores(raw.judge, [text] * 3, drawn.features)
        np.testing.assert_allclose(row["scores"], scores, atol=1e-5)
        kept = drawn.features[int(np.argmax(scores))]
        np.testing.assert_allclose(np.asarray(row["features"]), kept, atol=1e-6)
        assert np.asarray(row["joints"]).shape == (frames, 22, 3)
    assert any(np.argmax(row["scores"]) != 0 for row in best)  # so keeping the first draw would fail
    # A row's pick depends only on its own text, length and seed.
    alone = model.predict(request.iloc[1:], params=params)
    assert np.array_equal(np.asarray(alone[0]["joints"]), np.asarray(best[1]["joints"]))
    json.dumps(best)


@pytest.mark.slow
def test_generate_picks_with_the_judge_its_bundle_carries(
    judged_model, registered, store, tmp_path, monkeypatch
):
    """`mmm generate --candidates` on a registered bundle, without --judge, uses the evaluator the
    bundle was logged with, not whatever the evaluator champion is now: here the store it asks
    for the champion holds no evaluator at all."""
    import argparse

    from mmm.cli.generate import load_best_of_judge
    from mmm.evaluation.evaluators import load_evaluator
    from mmm.generation.model import TextToMotion
    from mmm.resolve import ModelNotFound

    monkeypatch.chdir(tmp_path)  # the bundle download cache and the newest-run search are relative
    uri = f"models:/{NAME}-judged/{judged_model['info'].registered_model_version}"
    model = TextToMotion.load(uri, tracking_uri=store)
    assert Path(model.judge_checkpoint).read_bytes() == Path(judged_model["judge"]).read_bytes()
    empty = argparse.Namespace(judge=None, tracking_uri=f"sqlite:///{tmp_path / 'empty.db'}", device="cpu")
    judge = load_best_of_judge(empty, model)
    assert judge.identity == load_evaluator(judged_model["judge"], store).identity
    # A bundle without a judge falls back to the champion, of which that store has none.
    plain = TextToMotion.load(registered["uri"], tracking_uri=store)
    assert plain.judge_checkpoint is None
    with pytest.raises(ModelNotFound):
        load_best_of_judge(empty, plain)


@pytest.mark.slow
def test_candidates_are_refused_without_a_judge_or_out_of_range(judged_model, served_model):
    from mlflow.exceptions import MlflowException

    request = pd.DataFrame({"text": ["a person walks"], "length": [40]})
    with pytest.raises(
        MlflowException, match="candidates 4 needs a judge, and this bundle carries none"
    ) as err:
        served_model.predict(request, params={"candidates": 4})
    assert err.value.get_http_status_code() == 400
    raw = judged_model["model"].unwrap_python_model()
    for bad in (0, 17, 2.5, "four"):
        with pytest.raises(MlflowException, match=f"candidates {bad!r} is not allowed") as err:
            raw.predict(None, request, params={"candidates": bad})
        assert err.value.get_http_status_code() == 400
    # JSON may carry 2 as 2.0.
    assert raw.predict(None, request, params={"candidates": 2.0})[0]["candidates"] == 2


def test_a_judge_must_read_the_models_features_and_captions(tmp_path):
    from mmm.evaluation.contrastive import ContrastiveEvaluator
    from mmm.fingerprint import tensors_fingerprint
    from mmm.registry.bundle import JudgeMismatch, describe_judge
    from mmm.training.configs import ContrastiveModelConfig

    cfg = ContrastiveModelConfig(hidden_dim=8, embed_dim=8, text_hidden_dim=8)
    evaluator = ContrastiveEvaluator(263, 16, cfg)
    state = {f"evaluator.{k}": v for k, v in evaluator.state_dict().items()}
    hp = {
        "feature_dim": 263,
        "sentence_dim": 16,
        "model": vars(cfg),
        "text_encoder": {"name": "minilm", "identity": "minilm-abc"},
    }
    path = tmp_path / "judge.ckpt"
    torch.save({"state_dict": state, "hyper_parameters": hp}, path)
    ok = {"feature_dim": 263, "text_encoder": "minilm-abc"}
    assert describe_judge(path, ok) == "contrastive-" + tensors_fingerprint(evaluator.state_dict())
    with pytest.raises(
        JudgeMismatch, match="trained on 263-dimensional motion features but the model makes 251"
    ):
        describe_judge(path, {**ok, "feature_dim": 251})
    with pytest.raises(
        JudgeMismatch, match="reads captions with text encoder minilm-abc, the model with clip-x"
    ):
        describe_judge(path, {**ok, "text_encoder": "clip-x"})


def test_importing_the_bundle_asks_nothing_of_the_user():
    """MLflow warned at every import of the pyfunc class (every promote and serve) that `predict`
    had no type hints; it has one now, which MLflow accepts without validating through it."""
    result = subprocess.run(
        [sys.executable, "-W", "default", "-c", "import mmm.registry.bundle"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "Add type hints" not in result.stderr and "Warning" not in result.stderr, result.stderr

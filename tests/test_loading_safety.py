"""Loading safety: every bad file a clear error naming it (CLI exit 2, no traceback), recorded paths
followed only inside outputs/, fingerprints checked before use, nothing that can run code.

Checkpoints are written the way the trainers write them (state_dict, hyper_parameters and the
weights' fingerprint) from tiny hand-built modules: nothing is trained here.
"""

import pickle
import re
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from mmm.checkpoints import FINGERPRINT_KEY, CheckpointError, load_checkpoint, text_encoder_options
from mmm.cli import main
from mmm.data.arrays import load_array, load_arrays
from mmm.data.humanml3d import DataError, load_motion
from mmm.fingerprint import tensors_fingerprint
from mmm.generation.model import TextToMotion
from mmm.optim import OptimConfig
from mmm.resolve import ModelNotFound, resolve_checkpoint
from mmm.tokenizer.configs import TokenizerLossConfig
from mmm.tokenizer.load import load_tokenizer_checkpoint
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.network import TokenizerConfig
from mmm.transformer.configs import CorruptionConfig
from mmm.transformer.module import MaskedTransformerModule, stage2_codebooks
from mmm.transformer.network import TransformerConfig

SRC = Path(__file__).resolve().parent.parent / "src"
UNKNOWN_RUN = "0123456789abcdef0123456789abcdef"


def save_like_trainer(module, path: Path) -> Path:
    """The fields a Lightning checkpoint of this package holds, with RunState's fingerprint."""
    state = module.state_dict()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "state_dict": state,
            "hyper_parameters": dict(module.hparams),
            "global_step": 4,
            FINGERPRINT_KEY: tensors_fingerprint(state),
        },
        path,
    )
    return path


def build_pair(root: Path, stage1_dir: Path, seed: int):
    """A stage-1 checkpoint under `stage1_dir` and a stage-2 checkpoint under root/outputs that records it."""
    from mmm.text import build_text_encoder

    torch.manual_seed(seed)
    tokenizer = TokenizerModule(
        263, TokenizerConfig(width=16, num_codes=32, code_dim=8), OptimConfig(), TokenizerLossConfig()
    )
    stage1_path = save_like_trainer(tokenizer, stage1_dir / "checkpoints" / "best.ckpt")
    identity = tensors_fingerprint(tokenizer.state_dict())
    encoder = build_text_encoder("minilm")
    codebook, _ = stage2_codebooks(tokenizer)
    transformer = MaskedTransformerModule(
        codebook,
        TransformerConfig(embed_dim=32, num_heads=2, num_layers=2, dropout=0.0),
        OptimConfig(),
        CorruptionConfig(),
        encoder.sentence_dim,
        encoder.word_dim,
        {"reference": str(stage1_path), "run_id": None, "identity": identity, "checkpoint": str(stage1_path)},
        {"name": encoder.name, "identity": encoder.identity},
    )
    stage2_path = save_like_trainer(
        transformer, root / "outputs" / "stage2" / "run" / "checkpoints" / "best.ckpt"
    )
    return stage1_path, stage2_path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """root/outputs/{stage1,stage2}: a pair inside outputs/; elsewhere/: a stage-2 checkpoint whose
    stage-1 model lies outside outputs/; and every kind of bad file."""
    root = tmp_path_factory.mktemp("loading")
    stage1, stage2 = build_pair(root, root / "outputs" / "stage1" / "run", seed=0)
    other = tmp_path_factory.mktemp("other")
    far_stage1, far_stage2 = build_pair(other, root / "elsewhere" / "stage1", seed=1)
    bad = root / "bad"
    bad.mkdir()
    (bad / "random.ckpt").write_bytes(np.random.default_rng(0).bytes(4096))
    (bad / "notes.ckpt").write_text("this is a text file, not a checkpoint\n")
    raw = stage2.read_bytes()
    (bad / "truncated.ckpt").write_bytes(raw[: len(raw) // 2])
    (bad / "folder.ckpt").mkdir()
    ckpt = torch.load(stage2, weights_only=True)
    name = next(k for k, v in ckpt["state_dict"].items() if v.is_floating_point())
    ckpt["state_dict"][name] = ckpt["state_dict"][name] + 0.5  # the recorded fingerprint is left as it was
    torch.save(ckpt, bad / "tampered.ckpt")
    (bad / "corrupt.npy").write_bytes(b"\x93NUMPY\x01\x00garbage")
    np.save(bad / "strings.npy", np.full((60, 263), "1.0"))
    np.save(bad / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    return {
        "root": root,
        "stage1": stage1,
        "stage2": stage2,
        "far_stage1": far_stage1,
        "far_stage2": far_stage2,
        "bad": bad,
    }


def run_cli(argv, capsys):
    code = main(argv)
    err = capsys.readouterr().err
    return code, err


def generate_argv(model, out, *extra):
    return [
        "generate",
        "--text",
        "a person walks forward",
        "--length",
        "40",
        "--model",
        str(model),
        "--out",
        str(out),
        *extra,
    ]


# -- the CLI: exit 2 and a message naming the file ------------------------------------------------
@pytest.mark.parametrize(
    "name, found",
    [
        ("random.ckpt", "is not a PyTorch checkpoint"),
        ("notes.ckpt", "is not a PyTorch checkpoint"),
        ("truncated.ckpt", "truncated or damaged"),
        ("folder.ckpt", "is a folder"),
        ("tampered.ckpt", "fingerprint"),
    ],
)
def test_generate_refuses_a_bad_model_file(files, tmp_path, monkeypatch, capsys, name, found):
    monkeypatch.chdir(files["root"])
    path = files["bad"] / name
    code, err = run_cli(
        generate_argv(path, tmp_path / "out", "--tracking-uri", f"sqlite:///{tmp_path}/mlflow.db"), capsys
    )
    assert code == 2 and str(path) in err and found in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
    with pytest.raises(CheckpointError, match=re.escape(str(path))):
        TextToMotion.from_files(path)


def test_generate_refuses_a_stage1_checkpoint_as_the_model(files, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(files["root"])
    code, err = run_cli(generate_argv(files["stage1"], tmp_path / "out"), capsys)
    assert code == 2 and f"{files['stage1']} is a stage-1 (motion tokenizer) checkpoint, not a stage-2" in err
    assert "--stage1 PATH" in err  # where it belongs
    with pytest.raises(CheckpointError, match="is a stage-1"):
        TextToMotion.from_files(files["stage1"])


@pytest.mark.slow
def test_generate_refuses_an_unknown_run_id(files, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    # No store there: said so, and none is created.
    code, err = run_cli(generate_argv(UNKNOWN_RUN, tmp_path / "out", "--tracking-uri", uri), capsys)
    assert code == 2 and f"{UNKNOWN_RUN}: no MLflow store at {uri}" in err and "Traceback" not in err
    assert not (tmp_path / "mlflow.db").exists()
    # A store without that run.
    from mlflow.tracking import MlflowClient

    MlflowClient(uri).search_experiments()
    code, err = run_cli(generate_argv(UNKNOWN_RUN, tmp_path / "out", "--tracking-uri", uri), capsys)
    assert code == 2 and f"{UNKNOWN_RUN}: no such run" in err and "Traceback" not in err
    with pytest.raises(ModelNotFound, match=UNKNOWN_RUN):
        resolve_checkpoint(
            UNKNOWN_RUN,
            uri,
            "mmm-stage2",
            "outputs/stage2",
            "text-to-motion model",
            "make train-stage2",
            "--model",
        )


@pytest.mark.slow
def test_generate_follows_a_recorded_stage1_file_only_inside_outputs(files, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(files["root"])
    # Inside outputs/: the recorded stage-1 file is used.
    code, err = run_cli(generate_argv(files["stage2"], tmp_path / "inside"), capsys)
    assert code == 0, err
    assert np.load(tmp_path / "inside" / "0" / "features.npy").shape == (40, 263)
    # Elsewhere: refused, naming the recorded file and how to pass it.
    code, err = run_cli(generate_argv(files["far_stage2"], tmp_path / "far"), capsys)
    assert (
        code == 2
        and f"recorded as {files['far_stage1']}, outside outputs/" in err
        and f"--stage1 {files['far_stage1']}" in err
    )
    assert not (tmp_path / "far").exists()
    with pytest.raises(CheckpointError, match="outside outputs/"):
        TextToMotion.from_files(files["far_stage2"])
    # Named by the user: used (its fingerprint checked as always).
    code, err = run_cli(
        generate_argv(files["far_stage2"], tmp_path / "named", "--stage1", str(files["far_stage1"])), capsys
    )
    assert code == 0, err
    model = TextToMotion.from_files(files["far_stage2"], files["far_stage1"])
    assert model.identity["stage1"]["identity"] == tensors_fingerprint(model.tokenizer.state_dict())


def test_evaluate_takes_the_recorded_stage1_file_when_named(files, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(files["root"])
    argv = ["evaluate", f"text2motion={files['far_stage2']}", "what=[adherence]"]
    argv.append(f"data.root={tmp_path / 'none'}")
    code, err = run_cli(argv, capsys)
    assert code == 2 and f"stage1={files['far_stage1']}" in err  # how to name it, for this command
    # Named: the model loads (its fingerprint checked) and the run goes on to the data, missing here.
    code, err = run_cli(argv + [f"stage1={files['far_stage1']}"], capsys)
    assert code == 2 and "outside outputs/" not in err and str(tmp_path / "none") in err


def test_a_stage1_model_with_other_weights_is_refused(files, monkeypatch):
    monkeypatch.chdir(files["root"])
    with pytest.raises(CheckpointError, match="the tokens would not mean the same codes"):
        TextToMotion.from_files(files["far_stage2"], files["stage1"])  # the other pair's tokenizer


def test_the_registry_fingerprints_are_checked(files, monkeypatch):
    monkeypatch.chdir(files["root"])
    actual = tensors_fingerprint(torch.load(files["stage2"], weights_only=True)["state_dict"])
    model = TextToMotion.from_files(files["stage2"], expected_identity={"transformer": actual})
    assert model.identity["transformer"] == actual
    with pytest.raises(
        CheckpointError, match=f"fingerprint {actual}, but {'f' * 16} was expected by the registry"
    ):
        TextToMotion.from_files(files["stage2"], expected_identity={"transformer": "f" * 16})
    with pytest.raises(CheckpointError, match="the registry records"):
        TextToMotion.from_files(files["stage2"], expected_identity={"stage1": "e" * 16})


@pytest.mark.parametrize(
    "name, found",
    [
        ("corrupt.npy", "not a readable .npy array"),
        ("strings.npy", "holds <U3 values, not numbers"),
        ("objects.npy", "not a readable .npy array"),  # allow_pickle=False refuses object arrays
    ],
)
def test_edit_refuses_a_bad_source_file(files, tmp_path, monkeypatch, capsys, name, found):
    monkeypatch.chdir(files["root"])
    path = files["bad"] / name
    argv = [
        "edit",
        "complete",
        "--source",
        str(path),
        "--keep",
        "0:40",
        "--model",
        str(files["stage2"]),
        "--out",
        str(tmp_path / "out"),
    ]
    code, err = run_cli(argv, capsys)
    assert code == 2 and str(path) in err and found in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
    with pytest.raises(DataError, match=re.escape(str(path))):
        load_array(path, "motion")


@pytest.mark.parametrize(
    "name, found",
    [
        ("random.ckpt", "is not a PyTorch checkpoint"),
        ("truncated.ckpt", "truncated or damaged"),
        ("folder.ckpt", "is a folder"),
    ],
)
def test_tokenize_refuses_a_bad_stage1_file(files, tmp_path, monkeypatch, capsys, name, found):
    monkeypatch.chdir(tmp_path)
    path = files["bad"] / name
    code, err = run_cli(
        ["tokenize", f"stage1={path}", f"logger.tracking_uri=sqlite:///{tmp_path}/mlflow.db"], capsys
    )
    assert code == 2 and str(path) in err and found in err and "Traceback" not in err


@pytest.mark.slow
def test_tokenize_refuses_a_stage2_checkpoint_and_an_unknown_run(files, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    uri = f"logger.tracking_uri=sqlite:///{tmp_path}/mlflow.db"
    code, err = run_cli(["tokenize", f"stage1={files['stage2']}", uri], capsys)
    assert (
        code == 2
        and f"{files['stage2']} is a stage-2 (text-to-motion transformer) checkpoint, not a stage-1" in err
    )
    code, err = run_cli(["tokenize", f"stage1={UNKNOWN_RUN}", uri], capsys)
    assert code == 2 and f"{UNKNOWN_RUN}: no MLflow store at" in err and "Traceback" not in err


# -- the Python API: the package's exception types ------------------------------------------------
@pytest.mark.parametrize(
    "name", ["random.ckpt", "notes.ckpt", "truncated.ckpt", "folder.ckpt", "tampered.ckpt", "missing.ckpt"]
)
def test_load_checkpoint_raises_checkpoint_error(files, name):
    path = files["bad"] / name
    with pytest.raises(CheckpointError, match=re.escape(str(path))):
        load_checkpoint(path, "stage2")
    with pytest.raises(CheckpointError, match=re.escape(str(path))):
        load_tokenizer_checkpoint(path)


class _RunsCode:
    def __reduce__(self):
        return (Path.mkdir, (Path("pwned"),))


def test_a_checkpoint_that_would_run_code_is_refused_unrun(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": {"feature_dim": 263, "model": _RunsCode()}}, path)
    with pytest.raises(
        CheckpointError,
        match="evil.ckpt is not a stage-1 .* holds objects other than tensors .* never unpickles",
    ):
        load_tokenizer_checkpoint(path)
    assert not (tmp_path / "pwned").exists()


def test_every_loader_refuses_the_wrong_kind(files):
    from mmm.evaluation.contrastive import load_contrastive_evaluator
    from mmm.generation.length import load_length_estimator

    assert load_checkpoint(files["stage2"], "stage2")["hyper_parameters"]["codebook_shape"] == [32, 8]
    with pytest.raises(CheckpointError, match="is a stage-2 .* not a stage-1"):
        load_tokenizer_checkpoint(files["stage2"])
    with pytest.raises(CheckpointError, match="is a stage-2 .* not a length estimator checkpoint"):
        load_length_estimator(files["stage2"])
    with pytest.raises(CheckpointError, match="is a stage-1 .* not a contrastive evaluator checkpoint"):
        load_contrastive_evaluator(files["stage1"])


def test_a_released_file_is_named_as_such(tmp_path):
    path = tmp_path / "net_last.pth"
    torch.save({"net": {"w": torch.ones(2)}}, path)
    with pytest.raises(CheckpointError, match="a released MMM file .* `mmm import released`"):
        load_checkpoint(path, "stage1")


def test_run_state_records_the_weights_fingerprint():
    from mmm.callbacks.checkpoints import RunState

    state = {"a": torch.arange(4.0), "b": torch.ones(2, 2)}
    checkpoint = {"state_dict": state}
    trainer = types.SimpleNamespace(loggers=[], world_size=1, max_steps=1500)
    RunState().on_save_checkpoint(trainer, None, checkpoint)
    assert checkpoint[FINGERPRINT_KEY] == tensors_fingerprint(state)
    assert checkpoint["schedule_steps"] == 1500  # what placed optim.final_share's drop


def test_text_encoder_files_are_read_only_inside_outputs_or_when_named(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    inside = tmp_path / "outputs" / "clip.bin"
    inside.parent.mkdir()
    inside.write_bytes(b"w")
    far = tmp_path / "elsewhere.bin"
    far.write_bytes(b"w")
    recorded = {
        "name": "clip-vit-b32",
        "identity": "x",
        "weights": str(inside),
        "vocab": None,
        "precision": "float32",
    }
    assert text_encoder_options(recorded, None, "s2.ckpt") == (
        "clip-vit-b32",
        {"weights": str(inside), "precision": "float32"},
    )
    with pytest.raises(
        CheckpointError,
        match=f"weights file {re.escape(str(far))}, which is outside outputs/.*--clip-weights PATH",
    ):
        text_encoder_options({**recorded, "weights": str(far)}, None, "s2.ckpt")
    given = text_encoder_options({**recorded, "weights": str(far)}, {"weights": str(far)}, "s2.ckpt")
    assert given[1]["weights"] == str(far)
    with pytest.raises(CheckpointError, match="model_dir"):
        text_encoder_options({"name": "minilm", "identity": "x", "model_dir": str(far)}, None, "s2.ckpt")


# -- numpy files ---------------------------------------------------------------------------------
def test_arrays_and_caches_refuse_bad_files(files, tmp_path):
    from mmm.data.tokens import TokenCache

    with pytest.raises(DataError, match="holds <U3 values, not numbers"):
        load_motion(files["bad"] / "strings.npy", 263)
    with pytest.raises(DataError, match="is a folder"):
        load_array(files["bad"] / "folder.ckpt", "motion")
    np.savez(tmp_path / "tokens.npz", **{f"{i:06d}": np.arange(50, dtype=np.int16) for i in range(40)})
    assert len(load_arrays(tmp_path / "tokens.npz", "token cache")) == 40
    cache = tmp_path / "cache"
    cache.mkdir()
    raw = (tmp_path / "tokens.npz").read_bytes()
    (cache / "tokens.npz").write_bytes(raw[: len(raw) // 2])
    (cache / "meta.json").write_text('{"splits": ["train"]}')
    with pytest.raises(
        DataError,
        match=f"{re.escape(str(cache / 'tokens.npz'))}: not a readable .npz archive.*delete the folder",
    ):
        len(TokenCache(cache))
    (cache / "meta.json").write_text("{")
    with pytest.raises(DataError, match="meta.json: unreadable token cache description"):
        TokenCache(cache)


def test_glove_files_that_fail_to_read_are_named(tmp_path):
    from collections import OrderedDict

    from mmm.evaluation.t2m import WordVectorizer

    glove = tmp_path / "glove"
    glove.mkdir()
    np.save(glove / "our_vab_data.npy", np.ones((2, 300), np.float32))
    (glove / "our_vab_words.pkl").write_bytes(pickle.dumps(["unk", "walk"]))
    (glove / "our_vab_idx.pkl").write_bytes(pickle.dumps({"unk": 0, "walk": 1}))
    assert WordVectorizer.load(glove).dim == 300
    (glove / "our_vab_idx.pkl").write_bytes(pickle.dumps({"unk": 0, "walk": 1})[:10])  # truncated
    with pytest.raises(DataError, match="our_vab_idx.pkl: not a readable vocabulary pickle"):
        WordVectorizer.load(glove)
    (glove / "our_vab_idx.pkl").write_bytes(
        pickle.dumps(OrderedDict(unk=0, walk=1))
    )  # a class outside the whitelist
    with pytest.raises(
        DataError,
        match="our_vab_idx.pkl: not a readable vocabulary pickle .*refusing to load collections.OrderedDict",
    ):
        WordVectorizer.load(glove)
    (glove / "our_vab_idx.pkl").write_bytes(pickle.dumps({"unk": 0, "walk": 1}))
    np.save(glove / "our_vab_data.npy", np.full((2, 300), "x"))
    with pytest.raises(DataError, match="our_vab_data.npy: the GloVe word vectors holds <U1 values"):
        WordVectorizer.load(glove)


# -- nothing that can run code ---------------------------------------------------------------------
def test_no_loader_that_can_run_code_in_the_package():
    offenders = [
        f"{path.relative_to(SRC)}: {needle}"
        for path in sorted(SRC.rglob("*.py"))
        for needle in ("torch.jit.load", "pickle.load(", "allow_pickle=True")
        if needle in path.read_text()
    ]
    assert offenders == []

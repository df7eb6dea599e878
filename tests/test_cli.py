"""The `mmm` command line: conversions and errors (exit code 2, message naming file and shape)."""

import os
import subprocess
import sys

import numpy as np
import pytest

import mmm
from mmm.cli import main


def test_convert_features_to_joints_and_back(reference_dir, tmp_path):
    features = reference_dir / "humanml3d/new_joint_vecs/012314.npy"
    joints_out, features_out = tmp_path / "j.npy", tmp_path / "sub/f.npy"
    assert main(["convert", "features-to-joints", str(features), str(joints_out)]) == 0
    joints = np.load(joints_out)
    assert joints.shape == (170, 22, 3) and joints.dtype == np.float32
    assert np.abs(joints - np.load(reference_dir / "humanml3d/new_joints/012314.npy")).max() < 1e-5
    assert main(["convert", "joints-to-features", str(joints_out), str(features_out)]) == 0
    back = np.load(features_out)
    assert back.shape == (169, 263)
    assert np.abs(back[:89] - np.load(features)[:89]).max() < 2e-5
    assert not list(tmp_path.glob("**/.*tmp*"))  # atomic writes leave nothing behind
    # An existing output is replaced only when asked: first refused and kept, then replaced.
    kept = joints_out.read_bytes()
    assert main(["convert", "joints-to-features", str(features_out), str(joints_out)]) == 2
    assert joints_out.read_bytes() == kept
    assert main(["convert", "joints-to-features", str(joints_out), str(joints_out), "--overwrite"]) == 0
    assert np.load(joints_out).shape == (169, 263)


def test_convert_reads_other_byte_orders_and_takes_out_like_the_other_commands(
    reference_dir, tmp_path, capsys
):
    """Files written on other machines (big-endian float32, float64, Fortran order) convert to the
    same result; the output may be given as --out, once."""
    joints = np.load(reference_dir / "humanml3d/new_joints/012314.npy")
    expected = tmp_path / "expected.npy"
    assert (
        main(
            [
                "convert",
                "joints-to-features",
                str(reference_dir / "humanml3d/new_joints/012314.npy"),
                str(expected),
            ]
        )
        == 0
    )
    for name, array in {
        "big_endian": joints.astype(">f4"),
        "float64": joints.astype(np.float64),
        "fortran": np.asfortranarray(joints),
    }.items():
        source, out = tmp_path / f"{name}.npy", tmp_path / f"{name}_features.npy"
        np.save(source, array)
        assert main(["convert", "joints-to-features", str(source), "--out", str(out)]) == 0
        assert np.array_equal(np.load(out), np.load(expected)), name
    capsys.readouterr()
    for outputs in ([], [str(tmp_path / "a.npy"), "--out", str(tmp_path / "b.npy")]):
        assert main(["convert", "joints-to-features", str(source), *outputs]) == 2
        assert "give the .npy to write once" in capsys.readouterr().err
    assert not (tmp_path / "a.npy").exists() and not (tmp_path / "b.npy").exists()


@pytest.mark.parametrize(
    "direction, array, message",
    [
        (
            "joints-to-features",
            np.zeros((10, 263), np.float32),
            r"shape \(10, 263\), expected joints \(T, 22, 3\)",
        ),
        (
            "features-to-joints",
            np.zeros((10, 22, 3), np.float32),
            r"shape \(10, 22, 3\), expected features \(T, 263\)",
        ),
        ("features-to-joints", np.full((10, 263), np.nan, np.float32), "NaN/Inf"),
        # every joint at one point: no facing to measure, so the features would be NaN
        ("joints-to-features", np.zeros((10, 22, 3), np.float32), r"NaN/Inf in 9 of 9 frames .*degenerate"),
    ],
)
def test_convert_rejects_bad_input(tmp_path, capsys, direction, array, message):
    src, dst = tmp_path / "in.npy", tmp_path / "out.npy"
    np.save(src, array)
    assert main(["convert", direction, str(src), str(dst)]) == 2
    err = capsys.readouterr().err
    assert str(src) in err
    assert __import__("re").search(message, err)
    assert not dst.exists()


@pytest.mark.slow
def test_missing_input_and_console_entry_point(tmp_path):
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "mmm.cli",
            "convert",
            "features-to-joints",
            str(tmp_path / "nope.npy"),
            str(tmp_path / "o.npy"),
        ],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2
    assert "nope.npy: no such file" in result.stderr


def test_version_names_the_package_and_the_config_folder(tmp_path):
    env = {**os.environ, "MMM_CONF_DIR": str(tmp_path / "my-conf")}
    command = [sys.executable, "-m", "mmm.cli", "--version"]
    shown = subprocess.run(command, capture_output=True, text=True, env=env)
    assert shown.returncode == 0
    assert shown.stdout.strip() == f"mmm-motion {mmm.__version__}, configs from {tmp_path / 'my-conf'}"


def test_overrides_may_follow_an_option():
    from mmm.cli.app import parse_arguments

    after = parse_arguments(["train", "stage1", "--resume", "last", "trainer.max_steps=20", "seed=1"])
    assert after.resume == "last" and after.overrides == ["trainer.max_steps=20", "seed=1"]
    around = parse_arguments(["train", "stage1", "data=kit", "--resume", "last", "trainer.max_steps=20"])
    assert around.overrides == ["data=kit", "trainer.max_steps=20"]
    with pytest.raises(SystemExit) as refused:
        parse_arguments(["train", "stage1", "--resume", "last", "--bogus"])
    assert refused.value.code == 2
    with pytest.raises(SystemExit):  # a command without overrides takes no key=value
        parse_arguments(["render", "a.npy", "--out", "a.gif", "fps=5"])


def test_data_stats_writes_a_usable_std_for_a_constant_feature_and_names_a_foreign_mean(tmp_path, capsys):
    """Foot contacts that never change have Std 0, which every loader refuses: written as 1 (a
    constant feature normalizes to 0) and named; a saved Mean of another size is not compared."""
    from mmm.data.humanml3d import load_stats
    from tests.helpers import make_features, write_dataset

    clips = {}
    for i in range(4):
        features = make_features(60, i)
        features[:, -4:] = 1.0  # contacts constant over the whole dataset
        clips[f"{i:06d}"] = (features, ["a person walks#a/DET person/NOUN walk/VERB#0.0#0.0"])
    write_dataset(tmp_path, clips, {s: list(clips) for s in ("train", "val", "test")}, stats=False)
    np.save(tmp_path / "Mean.npy", np.zeros(251, np.float32))
    np.save(tmp_path / "Std.npy", np.ones(251, np.float32))
    assert main(["data", "stats", str(tmp_path), "--write"]) == 0
    out, err = capsys.readouterr()
    assert "the saved Mean.npy (251,) and Std.npy (251,) are not of this dataset's (263,)" in out
    assert "warning: Std is 0 for contacts (dims 259-262): constant over the dataset; written as 1" in err
    mean, std = load_stats(tmp_path, 263)  # refuses a zero or negative Std
    assert (
        std.shape == (263,) and np.all(std[-4:] == 1.0) and np.all(std[:-4] > 0) and np.all(mean[-4:] == 1.0)
    )


def test_data_check_reports_every_split_and_names_each_unusable_one(tmp_path, capsys):
    """A dataset whose val and test splits are both unusable: both are named in one run, and the
    usable train split is still reported."""
    from tests.helpers import write_dataset

    caption = ["a person walks#a/DET person/NOUN walk/VERB#0.0#0.0"]
    clips = {f"{i:06d}": (60, caption) for i in range(3)}
    clips["000009"] = (20, caption)  # below the 40-frame minimum
    write_dataset(tmp_path, clips, {"train": ["000000", "000001", "000002"], "val": ["000009"]})
    (tmp_path / "test.txt").write_text("\n")  # no ids at all
    assert main(["data", "check", str(tmp_path)]) == 2
    out, err = capsys.readouterr()
    assert "train: kept 3 items from 3 clips" in out, out
    assert "val: cannot be used (below)" in out and "test: cannot be used (below)" in out
    assert "mirrored ids in a different split from their original: not checked" in out
    error = err.strip().splitlines()[-1]
    assert error.startswith("error: 2 of 3 splits cannot be used: val: ")
    assert "no usable items in split 'val'" in error and "split file lists no ids" in error
    assert f"{tmp_path / 'val.txt'}" in error and f"{tmp_path / 'test.txt'}" in error


def test_models_alone_lists_and_takes_the_store_before_or_after_list(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    for args in (["models"], ["models", "list"]):
        assert main(args) == 2
        assert f"no MLflow store at {tmp_path / 'mlflow.db'}" in capsys.readouterr().err
    store = tmp_path / "elsewhere.db"
    uri = ["--tracking-uri", str(store)]
    for args in (["models", *uri, "list"], ["models", "list", *uri]):
        assert main(args) == 2
        assert f"no MLflow store at {store}" in capsys.readouterr().err

"""The package installed from its sdist or wheel, not from a checkout: it carries its configs.

conf/ sits beside src/ in the repository; setup.py copies it into the wheel as mmm/conf and
MANIFEST.in puts it in the sdist, so `pip install <the repository>` gives an `mmm` that composes
every config from any folder."""

import os
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

from mmm.config import ConfigError, compose, conf_dir

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md", "src", "conf")


def _conf_files() -> set[str]:
    return {p.relative_to(REPO / "conf").as_posix() for p in (REPO / "conf").rglob("*.yaml")}


def _run(*args, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """sdist of a copy of the sources (the build writes into the tree it builds), then a wheel
    built from the unpacked sdist (what `pip install <sdist>` does), installed to a folder."""
    out = tmp_path_factory.mktemp("packaging")
    tree = out / "tree"
    tree.mkdir()
    for name in SOURCES:
        source = REPO / name
        if source.is_dir():
            shutil.copytree(source, tree / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(source, tree / name)
    made = _run(sys.executable, "setup.py", "-q", "sdist", "-d", str(out / "sdist"), cwd=tree)
    assert made.returncode == 0, made.stderr
    (sdist,) = (out / "sdist").glob("*.tar.gz")
    with tarfile.open(sdist) as archive:
        archive.extractall(out / "unpacked", filter="data")
        sdist_names = archive.getnames()
    (unpacked,) = (out / "unpacked").iterdir()
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    wheels = str(out / "wheel")
    built = _run(*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", wheels, ".", cwd=unpacked)
    assert built.returncode == 0, built.stderr
    (wheel,) = (out / "wheel").glob("*.whl")
    target = out / "site"
    done = _run(*pip, "install", "--no-deps", "--target", str(target), str(wheel), cwd=out)
    assert done.returncode == 0, done.stderr
    return {"sdist_names": sdist_names, "wheel": wheel, "site": target, "out": out}


@pytest.mark.slow
def test_sdist_and_wheel_carry_every_config(installed):
    expected = _conf_files()
    assert len(expected) >= 30  # every group and recipe of conf/
    root = installed["sdist_names"][0].split("/")[0]
    in_sdist = {n.split(f"{root}/conf/", 1)[1] for n in installed["sdist_names"] if f"{root}/conf/" in n}
    assert expected <= in_sdist
    in_wheel = zipfile.ZipFile(installed["wheel"]).namelist()
    assert {n.removeprefix("mmm/conf/") for n in in_wheel if n.startswith("mmm/conf/")} == expected
    # Every module of the package is in the wheel too (the bundle's code file included).
    modules = {p.relative_to(REPO / "src").as_posix() for p in (REPO / "src" / "mmm").rglob("*.py")}
    assert modules <= set(in_wheel) and "mmm/registry/pyfunc_model.py" in modules


@pytest.mark.slow
def test_installed_package_composes_its_configs_from_any_folder(installed):
    site, elsewhere = installed["site"], installed["out"] / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "MMM_CONF_DIR"}
    env["PYTHONPATH"] = str(site)  # ahead of the checkout's editable install
    probe = (
        "import mmm.config as c; cfg = c.compose('train_stage2', ['model=paper', 'recipe=quality']); "
        "print(c.__file__); print(c.conf_dir()); "
        "print(cfg.model.transformer.num_layers, cfg.trainer.max_steps)"
    )
    shown = _run(sys.executable, "-c", probe, cwd=elsewhere, env=env)
    assert shown.returncode == 0, shown.stderr
    module_file, folder, numbers = shown.stdout.split("\n")[:3]
    assert Path(module_file).is_relative_to(site) and Path(folder) == site / "mmm" / "conf"
    # The paper's 18 layers (conf/model/paper.yaml) and the quality recipe's steps, as the checkout has them.
    checkout = compose("train_stage2", ["model=paper", "recipe=quality"])
    assert numbers.split() == ["18", str(checkout.trainer.max_steps)] and checkout.trainer.max_steps == 6300
    # The installed command line: a typo is refused by the installed configs' schema, not for a
    # missing conf/ (exit 2, the key named).
    command = (sys.executable, "-m", "mmm.cli", "train", "stage1", "model.bogus=1")
    refused = _run(*command, cwd=elsewhere, env=env)
    assert refused.returncode == 2, refused.stderr
    assert "Key 'bogus' not in 'ModelConfig'" in refused.stderr and "not found" not in refused.stderr
    assert not any(elsewhere.iterdir())  # a refused command writes nothing
    version = _run(sys.executable, "-m", "mmm.cli", "--version", cwd=elsewhere, env=env)
    assert version.stdout.strip().endswith(f"configs from {site / 'mmm' / 'conf'}")


def test_a_missing_config_folder_is_named_with_the_fix(tmp_path, monkeypatch):
    missing = tmp_path / "my-configs"
    monkeypatch.setenv("MMM_CONF_DIR", str(missing))
    assert conf_dir() == missing
    with pytest.raises(ConfigError) as refused:
        compose("train_stage1")
    message = str(refused.value)
    assert str(missing) in message and "MMM_CONF_DIR" in message and "reinstall" in message
    monkeypatch.delenv("MMM_CONF_DIR")
    assert conf_dir() == REPO / "conf"  # a checkout without a built copy reads its own conf/

"""The package's shape: no import cycle between modules, imports inside functions only where they
say why (the CLI keeps `mmm --help` fast; optional dependencies stay optional), one home for the
schedules and the model kinds."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted((SRC / "mmm").rglob("*.py")):
        name = ".".join(path.relative_to(SRC).with_suffix("").parts).removesuffix(".__init__")
        out[name] = path
    return out


def _imported(node, modules: dict[str, Path]) -> list[str]:
    """The package modules an import statement loads."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name in modules]
    if node.level or not node.module:
        return []
    found = [f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in modules]
    return found or ([node.module] if node.module in modules else [])


def _function_imports(tree: ast.Module):
    """Import statements inside a function body, with the statement that holds them."""
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for parent in ast.walk(fn):
                for child in ast.iter_child_nodes(parent):
                    if isinstance(child, (ast.Import, ast.ImportFrom)):
                        yield child, parent


def test_no_import_cycle_between_modules():
    modules = _modules()
    graph = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                graph[name].update(m for m in _imported(node, modules) if m != name)
    # A cycle is a module that reaches itself.
    cycles = []
    for start in graph:
        seen, stack = set(), list(graph[start])
        while stack:
            m = stack.pop()
            if m == start:
                cycles.append(start)
                break
            if m not in seen:
                seen.add(m)
                stack.extend(graph[m])
    assert cycles == [], f"modules on an import cycle: {cycles}"


# The README's layers (Layout), lowest first; a module may import its own layer and those below.
# The top-level modules (mmm.config, mmm.device, mmm.optim, ...) import none of these packages.
LAYERS = {
    **dict.fromkeys(("motion", "data", "text"), 0),
    **dict.fromkeys(("tokenizer", "transformer"), 1),
    "generation": 2,
    **dict.fromkeys(("training", "evaluation", "registry"), 3),
    "pipeline": 4,
    "cli": 5,
}


def test_no_module_imports_a_layer_above_it():
    upward, modules = [], _modules()
    for name, path in modules.items():
        parts = name.split(".")
        top_level = len(parts) == 1 or (len(parts) == 2 and path.name != "__init__.py")
        if not top_level and parts[1] not in LAYERS:
            continue  # callbacks, render, export, released: outside the README's order
        mine = -1 if top_level else LAYERS[parts[1]]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in _imported(node, modules):
                    layer = LAYERS.get((target.split(".") + [""])[1])
                    if layer is not None and layer > mine:
                        upward.append(f"{name}:{node.lineno} imports {target}")
    assert upward == [], upward


def test_imports_inside_functions_say_why():
    """Outside the CLI, an import inside a function carries a comment (on its line, the line above,
    or the `try` that guards it); inside the CLI each module says it once."""
    unexplained = []
    for name, path in _modules().items():
        lines = path.read_text().splitlines()
        tree = ast.parse("\n".join(lines))
        found = list(_function_imports(tree))
        if name.startswith("mmm.cli"):
            if found and not any("#" in line and "--help" in line for line in lines):
                unexplained.append(f"{name}: imports inside commands without the start-up comment")
            continue
        for node, parent in found:
            line, above = lines[node.lineno - 1], lines[node.lineno - 2]
            guard = lines[parent.lineno - 1] if isinstance(parent, ast.Try) else ""
            if "#" not in line and not above.strip().startswith("#") and "#" not in guard:
                unexplained.append(f"{name}:{node.lineno}: {line.strip()}")
    assert unexplained == []


def test_cli_help_does_not_load_torch_or_mlflow():
    code = (
        "import sys; from mmm.cli import build_parser; build_parser(); print(sorted(m for m in ('torch', "
        "'mlflow', 'lightning') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert out == "[]"


def _refusal_loads(argv: list[str], cwd: Path, libraries: tuple[str, ...], named: str = "") -> list[str]:
    """Run `mmm ARGV` in the empty folder `cwd`; it must exit 2 with an `error:` message naming
    `named` and write nothing. Returns which of `libraries` it imported."""
    code = (
        "import sys; from mmm.cli.app import main; rc = main(sys.argv[1:]); "
        f"print(rc, ','.join(sorted(m for m in {libraries!r} if m in sys.modules)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=cwd, check=True
    )
    rc, _, loaded = out.stdout.strip().partition(" ")
    assert rc == "2", out.stderr
    assert out.stderr.startswith("error: ") and named in out.stderr and list(cwd.iterdir()) == []
    return loaded.split(",") if loaded else []


@pytest.mark.parametrize(
    "argv",
    [
        ["generate", "--text", "a person walks", "--out", "o", "--temperature", "nan"],
        ["generate", "--text", "a person walks", "--out", "o", "--candidates", "17"],
        ["edit", "outpaint", "--source", "missing.npy", "--keep", "0:40", "--out", "o", "--seed", "-1"],
        ["generate-long", "--text", "a person walks", "--text", " ", "--out", "o"],
    ],
    ids=["generate", "generate candidates", "edit", "generate-long"],
)
def test_generation_commands_refuse_bad_input_before_loading_model_libraries(argv, tmp_path):
    """A refusal costs the interpreter, numpy and the checks (about 0.3 s), not the 2 s of importing
    torch nor the 6-10 s of Lightning and MLflow for a model that is never loaded."""
    assert _refusal_loads(argv, tmp_path, ("torch", "mlflow", "lightning")) == []


@pytest.mark.parametrize(
    "argv, named",
    [
        (["train", "stage1", "trainer.max_stepz=5"], "max_stepz"),
        (["train", "stage2", "corruption.cond_drop=1"], "corruption.cond_drop"),
        (["train", "stage1", "trainer.max_steps=5", "refine.steps=0"], "end before its first validation"),
        (["evaluate", "protocol.replications=0"], "protocol.replications=0"),
        (["ablate", "temperature", "grids.temperature=[]"], "grid is empty"),
        (["promote", "tokenizer", "criteria.tokenizer=[]"], "criteria.tokenizer is empty"),
        (["pipeline", "full", "overrides.stage2=[trainer.max_stepz=3]"], "overrides.stage2"),
        (["ablate", "cross-layers", "stage2_overrides=[trainer.max_stepz=3]"], "stage2 training"),
    ],
    ids=[
        "train key",
        "train value",
        "train schedule",
        "evaluate",
        "ablate",
        "promote",
        "pipeline step",
        "ablate training",
    ],
)
def test_config_commands_refuse_a_bad_config_before_loading_lightning_or_mlflow(argv, named, tmp_path):
    """The schemas (training/configs.py, evaluation/configs.py, ...) import torch at most: a bad
    config costs about 1.5 s, not the 7 s (13 s on a slow 2.6 GHz Xeon) of Lightning and MLflow; a
    pipeline refuses a later step's overrides, and a training sweep a later setting's, before the
    first trains."""
    assert _refusal_loads(argv, tmp_path, ("mlflow", "lightning", "torchmetrics"), named) == []


def test_every_configs_module_leaves_lightning_mlflow_and_torchmetrics_unimported():
    names = sorted(n for n in _modules() if n.endswith(".configs"))
    assert len(names) >= 8, names  # callbacks, data, evaluation, pipeline, registry, tokenizer, ...
    code = (
        f"import sys; [__import__(m) for m in {names!r}]; "
        "print(sorted(m for m in ('mlflow', 'lightning', 'torchmetrics') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stderr


def test_model_kind_names_have_one_home():
    """Experiment, folder and registered names of the model kinds are string constants only in
    kinds.py (docstrings and messages may mention them)."""
    from mmm.kinds import KINDS

    names = {v for k in KINDS.values() for v in (k.experiment, k.output_dir, k.registered, k.config) if v}
    spelled = []
    for path in sorted((SRC / "mmm").rglob("*.py")):
        if path.name == "kinds.py" and path.parent.name == "mmm":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and node.value in names:
                spelled.append(f"{path.relative_to(SRC)}:{node.lineno}: {node.value!r}")
    assert spelled == []


@pytest.mark.parametrize("name", ["uniform", "cosine"])
def test_training_schedule_names_reach_the_config_check(name):
    from mmm.transformer.configs import CorruptionConfig
    from mmm.transformer.schedules import TRAINING_SCHEDULES

    assert CorruptionConfig(mask_schedule=name).mask_schedule in TRAINING_SCHEDULES
    with pytest.raises(ValueError, match="corruption.mask_schedule must be one of uniform, cosine"):
        CorruptionConfig(mask_schedule="square")

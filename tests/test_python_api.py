"""The README's Python example ("Generating and editing"), run as written against a trained model."""

import contextlib
import io
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

README = Path(__file__).resolve().parents[1] / "README.md"
MARKER = "<!-- python-api"


def readme_python_block() -> str:
    text = README.read_text()
    assert MARKER in text, f"README.md has no {MARKER} ...--> marker before its Python example"
    after = text[text.index(MARKER) :]
    block = after[after.index("```python\n") + len("```python\n") :]
    return block[: block.index("```")]


@pytest.mark.slow
def test_readme_python_example_generates_renders_exports_and_edits(trained, tmp_path, monkeypatch):
    # The example reads ./mlflow.db: a copy of the fixture's store (its newest stage-2 run is the model).
    shutil.copyfile(Path(trained["out"]) / "mlflow.db", tmp_path / "mlflow.db")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(readme_python_block(), "README.md (python-api block)", "exec"), namespace)
    out, edited, long = namespace["out"], namespace["edited"], namespace["long"]
    # What the comments in the block say.
    assert [j.shape for j in out.joints] == [(120, 22, 3), (80, 22, 3)]
    assert [f.shape for f in out.features] == [(120, 263), (80, 263)]
    assert printed.getvalue().splitlines()[0] == "[(120, 22, 3), (80, 22, 3)]"
    with Image.open("generated.gif") as gif:
        assert gif.n_frames == 120  # one frame per motion frame, the longer motion's
    bvh = Path("walk.bvh").read_text()
    assert bvh.startswith("HIERARCHY") and "Frames: 120" in bvh
    # The edit keeps the source's frames where asked (through the tokenizer: close, not equal).
    assert edited.joints[0].shape == (120, 22, 3)
    kept = np.abs(edited.features[0][:40] - out.features[0][:40]).max()
    assert kept < np.abs(out.features[0][:40]).max()  # the same clip there, not another one
    assert edited.kept_codes[:10].all() and not edited.kept_codes[10:20].all()
    # The long motion runs through both prompts, each over its own frames.
    assert long.segments is not None and len(long.segments) == 2 and long.joints[0].shape[0] >= 160

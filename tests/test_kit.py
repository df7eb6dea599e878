"""KIT-ML end to end (`data=kit`: 21 joints, 251-d features, 12.5 fps, millimetres): statistics,
the data check, both stages trained briefly, generation, an edit and their outputs."""

import json

import numpy as np
import pytest

from mmm.cli import main
from mmm.motion.features import joints_to_features
from mmm.motion.skeleton import KIT_SKELETON
from tests.helpers import stage2_overrides, tiny_stage1_overrides, turning_walker

# KIT's 21 joints from HumanML3D's 22 (None: the heels, put under the ankles at the toes' height).
FROM_T2M = [0, 3, 6, 9, 15, 17, 19, 21, 16, 18, 20, 2, 5, 8, None, 11, 1, 4, 7, None, 10]


def kit_joints(frames: int, turns: float) -> np.ndarray:
    """(frames, 21, 3) millimetres: the tests' turning walker on KIT's skeleton."""
    t2m = turning_walker(frames=frames, turns=turns).numpy()
    joints = np.zeros((frames, 21, 3))
    for k, j in enumerate(FROM_T2M):
        if j is not None:
            joints[:, k] = t2m[:, j]
    for heel, ankle, toe in ((14, 8, 11), (19, 7, 10)):
        joints[:, heel] = t2m[:, ankle]
        joints[:, heel, 1] = t2m[:, toe, 1]
    return joints * 1000.0


@pytest.fixture(scope="module")
def kit(tmp_path_factory):
    from mmm.training.configs import load_stage1_config, load_stage2_config
    from mmm.training.stage1 import train_stage1
    from mmm.training.stage2 import train_stage2

    out = tmp_path_factory.mktemp("kit")
    root = out / "KIT-ML"
    for folder in ("new_joints", "new_joint_vecs", "texts"):
        (root / folder).mkdir(parents=True)
    ids = [f"{i:05d}" for i in range(20)]
    for i, motion_id in enumerate(ids):
        joints = kit_joints(70 + 2 * i, 0.1 + 0.04 * i)
        np.save(root / "new_joints" / f"{motion_id}.npy", joints.astype(np.float32))
        features = joints_to_features(joints, KIT_SKELETON).astype(np.float32)
        np.save(root / "new_joint_vecs" / f"{motion_id}.npy", features)
        caption = "a person turns#a/DET person/NOUN turn/VERB#0.0#0.0\n"
        (root / "texts" / f"{motion_id}.txt").write_text(caption)
    for split, part in (("train", ids[:16]), ("val", ids[16:18]), ("test", ids[18:])):
        (root / f"{split}.txt").write_text("\n".join(part) + "\n")
    assert main(["data", "stats", str(root), "--skeleton", "kit", "--write"]) == 0
    stage1 = train_stage1(load_stage1_config(tiny_stage1_overrides(root, out, "data=kit")))
    stage2 = train_stage2(
        load_stage2_config(["data=kit", *stage2_overrides(root, out, stage1=stage1.best_checkpoint)])
    )
    return {
        "root": root,
        "stage1": stage1.best_checkpoint,
        "stage2": stage2.best_checkpoint,
        "uri": f"sqlite:///{out}/mlflow.db",
    }


@pytest.mark.slow
def test_kit_statistics_and_check(kit, capsys):
    root = kit["root"]
    mean, std = np.load(root / "Mean.npy"), np.load(root / "Std.npy")
    assert mean.shape == std.shape == (251,) and np.isfinite(mean).all() and (std > 0).all()
    capsys.readouterr()
    assert main(["data", "check", str(root), "--skeleton", "kit"]) == 0
    report = capsys.readouterr().out
    assert "train: kept 16 items from 16 clips" in report and "test: kept 2 items from 2 clips" in report


@pytest.mark.slow
def test_kit_model_generates_edits_and_exports_at_its_own_rate(kit, tmp_path, capsys):
    # (the tokenizer named: its file lies outside outputs/, which a checkpoint's record is not trusted for)
    common = ["--model", kit["stage2"], "--stage1", kit["stage1"], "--tracking-uri", kit["uri"]]
    generate = ["generate", "--text", "a person turns", *common]
    assert main([*generate, "--length", "30", "--out", str(tmp_path / "g")]) == 0
    joints = np.load(tmp_path / "g/0/joints.npy")
    assert joints.shape == (30, 21, 3) and np.load(tmp_path / "g/0/features.npy").shape == (30, 251)
    assert 500 < np.ptp(joints[..., 1]) < 3000  # millimetres, as the dataset's joints
    bvh = (tmp_path / "g/0/motion.bvh").read_text()
    assert "Frames: 30" in bvh and "Frame Time: 0.08" in bvh  # 12.5 fps
    assert json.loads((tmp_path / "g/0/meta.json").read_text())["caption"] == "a person turns"
    # KIT's shortest motion is 24 frames, not HumanML3D's 40.
    capsys.readouterr()
    assert main([*generate, "--length", "20", "--out", str(tmp_path / "s")]) == 2
    assert "--length 20 frames is outside 24..196 (1.9-15.7 s at 12.5 fps)" in capsys.readouterr().err
    source = kit["root"] / "new_joint_vecs" / "00018.npy"
    frames = len(np.load(source))
    edit = ["edit", "inbetween", "--source", str(source), "--keep", f"0:16,{frames - 16}:{frames}"]
    assert main([*edit, "--text", "a person turns", "--out", str(tmp_path / "e"), *common]) == 0
    edited = np.load(tmp_path / "e/0/joints.npy")
    assert edited.shape == (frames, 21, 3)


@pytest.mark.slow
def test_kit_evaluation_samples_are_drawn_at_its_rate(kit, tmp_path):
    """`mmm evaluate`'s samples of a KIT-ML model: 21-joint motions in millimetres, at 12.5 fps."""
    from PIL import Image

    from mmm.data.humanml3d import load_items
    from mmm.evaluation.configs import EditingConfig
    from mmm.evaluation.samples import render_samples, spread
    from mmm.generation.model import TextToMotion

    model = TextToMotion.from_files(kit["stage2"], kit["stage1"])
    items, _ = load_items(kit["root"], "test", feature_dim=251, fps=12.5, min_length=24)
    gif, sheet = render_samples(model, "text2motion", items, kit["root"], tmp_path, 2, EditingConfig())
    with Image.open(gif) as image:
        assert image.width == 2 * 240 and image.info["duration"] == 80  # ms a frame: 12.5 fps
        assert image.n_frames == max(min(i.length, 196) // 4 * 4 for i in spread(items, 2))
    with Image.open(sheet) as image:
        assert image.size == (6 * 200, 4 * 200)

"""Stick-figure renderer: frame counts, sizes, orientation, camera following, errors, outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from mmm.motion.skeleton import KIT_SKELETON, T2M_SKELETON, forward_kinematics
from mmm.render import EncoderNotFound, frames, render_files, render_frames, render_gif, render_mp4, stick
from mmm.render.stick import COLOR

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "humanml3d"
LEFT = (COLOR["left_leg"], COLOR["left_arm"])
RIGHT = (COLOR["right_leg"], COLOR["right_arm"])
LIMBS = LEFT + RIGHT + (COLOR["spine"], COLOR["head"])


def rest_pose(
    num_frames: int = 1, step=(0.0, 0.0, 0.0), skeleton=T2M_SKELETON, offsets=None, root_height=0.83
):
    """The rest pose (arms hanging, facing +Z) for num_frames, the root moving by `step` per frame."""
    quats = torch.zeros(num_frames, skeleton.num_joints, 4, dtype=torch.float64)
    quats[..., 0] = 1.0
    root = torch.zeros(num_frames, 3, dtype=torch.float64)
    root[:, 1] = root_height
    root += torch.arange(num_frames, dtype=torch.float64)[:, None] * torch.tensor(step, dtype=torch.float64)
    return forward_kinematics(quats, root, skeleton, offsets).numpy()


def turned_around(joints: np.ndarray) -> np.ndarray:
    """Rotate 180 degrees about the vertical axis through the root at frame 0 (now facing -Z)."""
    out = joints.copy()
    out[..., 0] = 2 * joints[0, 0, 0] - joints[..., 0]
    out[..., 2] = 2 * joints[0, 0, 2] - joints[..., 2]
    return out


def indices(image: Image.Image) -> np.ndarray:
    assert image.mode == "P"
    return np.asarray(image)


def pixels_of(image: Image.Image, colors) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.nonzero(np.isin(indices(image), colors))
    return ys, xs


def reference(kind: str) -> np.ndarray:
    path = REFERENCE / kind / "012314.npy"
    if not path.exists():
        pytest.skip(f"reference data missing: {path}")
    return np.load(path)


def test_frame_count_and_image_size():
    short, long_ = rest_pose(7), rest_pose(12, step=(0.0, 0.0, 0.02))
    out = frames([short, long_], ["short", "long"], size=(150, 110))
    assert len(out) == 12
    assert {im.size for im in out} == {(300, 110)}
    one = frames(long_, size=(90, 100))
    assert len(one) == 12 and one[0].size == (90, 100)


def test_finished_motion_holds_its_last_frame_in_grey():
    out = frames([rest_pose(5), rest_pose(9)], size=(120, 120))
    first_panel = lambda im: indices(im)[:, :120]  # noqa: E731
    live, done = first_panel(out[4]), first_panel(out[8])
    assert np.isin(live, LEFT).sum() > 20 and not np.isin(live, COLOR["done_limb"]).any()
    assert not np.isin(done, LEFT + RIGHT).any() and np.isin(done, COLOR["done_limb"]).sum() > 20
    # the other panel is still live
    assert np.isin(indices(out[8])[:, 120:], LEFT).sum() > 20


def test_spans_name_the_part_playing_beside_the_counter():
    """A long motion's prompts are written beside the frame counter while they play ("transition"
    between them), in the text colour; nothing above the counter's line changes."""
    motion = rest_pose(12)
    shades = lambda role: [i for name, i in COLOR.items() if name.startswith(role)]  # noqa: E731
    spans = [(0, 5, "1. a person walks"), (8, 12, "2. a person jumps " + "very " * 40 + "high")]
    plain, named = frames(motion, size=(200, 160)), frames(motion, size=(200, 160), spans=[spans])
    line = 160 - 30  # the counter's line and below
    for t in range(12):
        a, b = indices(plain[t]), indices(named[t])
        assert np.array_equal(a[:line], b[:line]), t
        # the label starts past the counter: only there do the pixels differ
        counter_end = np.nonzero(np.isin(a[line:], shades("muted_text")).any(axis=0))[0].max()
        differ = np.nonzero((a != b).any(axis=0))[0]
        assert differ.size and differ.min() > counter_end, t
        assert np.isin(b[line:], shades("text")).sum() > 20 and not np.isin(a[line:], shades("text")).any(), t
    label = lambda t: indices(named[t])[line:, 50:]  # noqa: E731
    assert np.array_equal(label(0), label(4)) and np.array_equal(label(5), label(7))  # the same words
    assert not np.array_equal(label(4), label(5)) and not np.array_equal(label(7), label(8))
    # a label wider than the panel is cut to fit (ending in an ellipsis), not run off its edge
    text_columns = np.nonzero(np.isin(indices(named[9])[line:], shades("text")).any(axis=0))[0]
    assert 150 < text_columns.max() < 200 - 4


def test_joints_and_features_give_the_same_pixels():
    joints, features = reference("new_joints"), reference("new_joint_vecs")
    from_joints = frames([joints[:60]], ["012314"], size=(160, 160))
    from_features = frames([features[:60]], ["012314"], size=(160, 160))
    from_tensor = frames([torch.from_numpy(features[:60])], ["012314"], size=(160, 160))
    assert len(from_joints) == len(from_features) == 60
    for a, b, c in zip(from_joints, from_features, from_tensor):
        assert np.array_equal(indices(a), indices(b))
        assert np.array_equal(indices(b), indices(c))
    # and the motion does move: frames differ
    assert not np.array_equal(indices(from_joints[0]), indices(from_joints[40]))


def test_head_is_drawn_above_the_pelvis():
    pose = rest_pose(1)
    for joints in (pose, turned_around(pose)):
        im = frames([joints], size=(200, 200))[0]
        head_y, _ = pixels_of(im, [COLOR["head"]])
        leg_y, _ = pixels_of(im, [COLOR["left_leg"], COLOR["right_leg"]])
        assert len(head_y) > 30 and len(leg_y) > 30
        # the legs start at the hips, next to the pelvis: the whole head disc is above them
        assert head_y.max() < leg_y.min()
        assert head_y.mean() < 100 < leg_y.mean()
    upside_down = pose.copy()
    upside_down[..., 1] = 1.9 - pose[..., 1]
    im = frames([upside_down], size=(200, 200))[0]
    assert pixels_of(im, [COLOR["head"]])[0].mean() > pixels_of(im, [COLOR["left_leg"]])[0].mean()


def test_left_limbs_on_the_expected_side():
    # The camera stands in front of the body's start facing (+Z), turned towards +X (the body's
    # left): a body facing +Z shows its left limbs on the image's right, like a person facing
    # the viewer; turned around (facing -Z, back to the camera) they move to the image's left.
    pose = rest_pose(1)
    width = 200
    im = frames([pose], size=(width, 200))[0]
    _, left_x = pixels_of(im, LEFT)
    _, right_x = pixels_of(im, RIGHT)
    assert len(left_x) > 30 and len(right_x) > 30
    assert left_x.mean() > width / 2 > right_x.mean()
    assert left_x.mean() - right_x.mean() > 10
    im = frames([turned_around(pose)], size=(width, 200))[0]
    _, left_x = pixels_of(im, LEFT)
    _, right_x = pixels_of(im, RIGHT)
    assert left_x.mean() < width / 2 < right_x.mean()


def test_figure_stays_centred_while_the_floor_scrolls():
    moving = rest_pose(30, step=(0.0, 0.0, 0.03))  # walking along +Z, 0.6 m/s at 20 fps
    still = rest_pose(30)
    out_moving = frames([moving], size=(200, 200))
    out_still = frames([still], size=(200, 200))

    def centroid(im):
        ys, xs = pixels_of(im, LIMBS)
        return np.array([xs.mean(), ys.mean()])

    centres = np.array([centroid(im) for im in out_moving])
    assert np.abs(centres - centres[0]).max() < 1.0
    assert abs(centres[0, 0] - 100) < 20  # horizontally about the panel centre

    grid = lambda im: indices(im)[:170] == COLOR["grid"]  # noqa: E731  (above the frame counter)
    # still: the floor does not move; moving: the grid lines move under the figure
    assert np.array_equal(grid(out_still[0]), grid(out_still[5]))
    changed = (grid(out_moving[0]) != grid(out_moving[5])).sum()
    assert changed > 0.3 * grid(out_moving[0]).sum()
    # the path walked so far grows
    assert (indices(out_moving[20]) == COLOR["path"]).sum() > (indices(out_moving[5]) == COLOR["path"]).sum()


def test_kit_millimetres_are_scaled_to_metres():
    lengths = torch.full((21,), 200.0, dtype=torch.float64)  # millimetres
    lengths[0] = 0.0
    pose_mm = rest_pose(3, skeleton=KIT_SKELETON, offsets=KIT_SKELETON.offsets(lengths), root_height=800.0)
    assert pose_mm.shape == (3, 21, 3)
    im = frames([pose_mm], size=(200, 200))[0]
    ys, xs = pixels_of(im, LIMBS)
    assert len(ys) > 30
    height = ys.max() - ys.min()
    assert 40 < height < 160  # a 1.6 m figure, not 1600 m


def test_bad_files_raise_value_error_naming_file_and_shape(tmp_path):
    good = tmp_path / "good.npy"
    np.save(good, rest_pose(4).astype(np.float32))
    cases = {
        "wrong_shape.npy": (np.zeros((10, 22, 2), np.float32), ["(10, 22, 2)", "(T, 22, 3)", "(T, 263)"]),
        "wrong_width.npy": (np.zeros((10, 262), np.float32), ["(10, 262)", "(T, 263)"]),
        "empty.npy": (np.zeros((0, 22, 3), np.float32), ["(0, 22, 3)", "0 frames"]),
        "nan.npy": (
            np.where(np.arange(4)[:, None, None] == 2, np.nan, rest_pose(4)),
            ["NaN", "(4, 22, 3)", "[2]"],
        ),
    }
    for name, (array, expected) in cases.items():
        path = tmp_path / name
        np.save(path, array)
        with pytest.raises(ValueError) as err:
            render_files([good, path], tmp_path / "out.gif")
        message = str(err.value)
        assert name in message
        for text in expected:
            assert text in message, (text, message)
    missing = tmp_path / "missing.npy"
    with pytest.raises(ValueError, match="missing.npy.*not found"):
        render_files([missing], tmp_path / "out.gif")
    garbage = tmp_path / "garbage.npy"
    garbage.write_text("not an array")
    with pytest.raises(ValueError, match="garbage.npy.*cannot be loaded"):
        render_files([garbage], tmp_path / "out.gif")
    with pytest.raises(ValueError, match=r"out.webp.*\.gif, \.mp4 or \.png"):
        render_files([good], tmp_path / "out.webp")
    with pytest.raises(ValueError, match="captions"):
        frames([rest_pose(2)], ["a", "b"])
    (tmp_path / "folder.gif").mkdir()
    with pytest.raises(ValueError, match=r"folder.gif is a folder: name the file to write, e.g. .*motion"):
        render_files([good], tmp_path / "folder.gif")
    with pytest.raises(ValueError, match=r"good.npy is a file, not a folder"):
        render_files([good], good / "sub" / "out.gif")
    mask = tmp_path / "mask.npy"
    np.save(mask, np.ones((4, 22, 3), bool))
    with pytest.raises(ValueError, match=r"mask.npy: holds bool values, not motion numbers"):
        render_files([mask], tmp_path / "out.gif")
    # Longer than a render holds in memory: refused by the longest file, with the part that fits.
    long = tmp_path / "long.npy"
    np.save(long, rest_pose(3001).astype(np.float32))
    with pytest.raises(ValueError, match=r"long.npy: 3001 frames x 2 motion\(s\) .*\[:3000\]"):
        render_files([good, long], tmp_path / "out.gif")
    assert not (tmp_path / "out.gif").exists()


def test_render_command_replaces_a_file_only_when_asked(tmp_path, capsys):
    from mmm.cli import main

    path, out = tmp_path / "m.npy", tmp_path / "m.gif"
    np.save(path, rest_pose(5, step=(0.01, 0.0, 0.0)).astype(np.float32))
    assert main(["render", str(path), "--out", str(out)]) == 0
    first = out.read_bytes()
    assert main(["render", str(path), str(path), "--out", str(out)]) == 2
    assert "m.gif already exists: give --overwrite" in capsys.readouterr().err and out.read_bytes() == first
    assert main(["render", str(path), str(path), "--out", str(out), "--overwrite"]) == 0
    with Image.open(out) as gif:
        assert gif.size == (640, 320) and gif.n_frames == 5


def test_render_files_gif_with_skeleton_fps(tmp_path):
    path = tmp_path / "m.npy"
    np.save(path, rest_pose(6, step=(0.01, 0.0, 0.0)).astype(np.float32))
    (out,) = render_files([path, path], tmp_path / "two.gif", captions=["a", "b"])
    with Image.open(out) as gif:
        assert gif.n_frames == 6
        assert gif.size == (640, 320)
        assert gif.info["duration"] == 50  # 20 fps
        assert gif.info["loop"] == 0
    (png,) = render_files([path], tmp_path / "sheet.png")
    assert Image.open(png).size == (6 * 240, 240)
    # readable like every other output (the temporary file they are written to is owner-only)
    assert (out.stat().st_mode & 0o777, png.stat().st_mode & 0o777) == (0o644, 0o644)


def test_png_contact_sheet_size(tmp_path):
    out = render_frames(
        [rest_pose(10), rest_pose(25)], tmp_path / "sheet.png", ["one", "two"], num_frames=4, size=(100, 90)
    )
    with Image.open(out) as im:
        assert im.size == (400, 180)
        rgb = np.asarray(im.convert("RGB"))
    left_leg = np.all(rgb == stick.PALETTE["left_leg"], axis=-1)
    # every cell of both rows shows a figure
    for row in range(2):
        for col in range(4):
            assert left_leg[row * 90 : (row + 1) * 90, col * 100 : (col + 1) * 100].sum() > 5


def test_gif_leaves_no_temporary_file(tmp_path, monkeypatch):
    out = render_gif([rest_pose(8), rest_pose(5)], tmp_path / "anim.gif", ["a", "b"], fps=10.0, size=(96, 96))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim.gif"]
    with Image.open(out) as gif:
        assert gif.n_frames == 8 and gif.size == (192, 96) and gif.info["duration"] == 100

    # a failing writer leaves neither a partial output nor a temporary file
    def broken_save(self, fp, *args, **kwargs):
        Path(fp).write_bytes(b"GIF89a partial")
        raise OSError("disk full")

    monkeypatch.setattr(Image.Image, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        render_gif([rest_pose(3)], tmp_path / "broken.gif")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim.gif"]


def test_mp4_written_when_an_encoder_exists(tmp_path):
    if stick._find_ffmpeg() is None:
        pytest.skip("no MP4 encoder installed (pip install imageio-ffmpeg)")
    out = render_mp4(
        [rest_pose(10, step=(0, 0, 0.02)), rest_pose(6)], tmp_path / "a.mp4", ["a", "b"], size=(101, 99)
    )  # odd sizes are padded for yuv420p
    assert out == tmp_path / "a.mp4"
    data = out.read_bytes()
    assert len(data) > 500 and data[4:8] == b"ftyp"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mp4"]


def test_mp4_without_encoder(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(stick, "_find_ffmpeg", lambda: None)
    monkeypatch.setattr(stick, "_ffmpeg_missing_logged", False)
    with caplog.at_level("INFO", logger="mmm.render.stick"):
        assert render_mp4([rest_pose(3)], tmp_path / "a.mp4") is None
        assert render_mp4([rest_pose(3)], tmp_path / "a.mp4") is None
    assert sum("MP4 encoder" in r.message for r in caplog.records) == 1
    path = tmp_path / "m.npy"
    np.save(path, rest_pose(3))
    with pytest.raises(EncoderNotFound, match="b.mp4.*imageio-ffmpeg"):
        render_files([path], tmp_path / "b.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npy"]


def test_default_captions_come_from_a_samples_meta_json_else_the_file_names(tmp_path):
    from mmm.render.stick import default_captions

    generated, other, broken = (tmp_path / name for name in ("0", "1", "2"))
    for folder in (generated, other, broken):
        folder.mkdir()
    (generated / "meta.json").write_text('{"caption": "a person waves", "prompt": "a person waves"}')
    (broken / "meta.json").write_text("{not json")
    paths = [generated / "joints.npy", other / "joints.npy", broken / "joints.npy", tmp_path / "clip.npy"]
    assert default_captions(paths) == ["a person waves", "1/joints", "2/joints", "clip"]
    assert default_captions([other / "joints.npy"]) == ["joints"]  # a name alone when it is the only one

"""The synthetic dataset: on-disk layout, captions, labels, mirrors, splits, statistics, determinism."""

import json
import re

import numpy as np
import pytest
import torch

from mmm.data.synthetic import generate as gen
from mmm.data.synthetic.actions import PartSpec, make_motion
from mmm.data.synthetic.captions import LEXICON, TAGS, clip_captions, mirror_caption_line, mirror_params
from mmm.motion.features import FeatureLayout, joints_to_features, recover_from_ric, reference_std
from mmm.motion.skeleton import T2M_SKELETON, mirror_joints

NUM_CLIPS = 60
SEED = 7
PARAMS = {
    "stand": {},
    "raise_arms": {},
    "sit": {},
    "walk": {"direction": {"forward", "backward", "left", "right"}, "speed": {"slow", "normal", "fast"}},
    "run": {"direction": {"forward"}},
    "turn": {"side": {"left", "right"}, "angle": {90, 180}},
    "circle": {"side": {"clockwise", "counterclockwise"}},
    "jump": {"count": {1, 2, 3}, "mode": {"in_place", "forward"}},
    "squat": {"count": {1, 2, 3}},
    "wave": {"hand": {"left", "right", "both"}},
    "punch": {"hand": {"left", "right", "both"}},
    "kick": {"foot": {"left", "right"}},
}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth") / "ds"
    summary = gen.generate_dataset(root, num_clips=NUM_CLIPS, seed=SEED, progress=False, workers=1)
    return root, summary


def ids_of(root, split="all"):
    return [line.strip() for line in (root / f"{split}.txt").read_text().splitlines() if line.strip()]


@pytest.mark.slow
def test_layout_shapes_and_dtypes(dataset):
    root, summary = dataset
    clip_ids = [f"{i:06d}" for i in range(NUM_CLIPS)]
    expected = sorted(clip_ids + ["M" + i for i in clip_ids])
    assert summary["clips"] == NUM_CLIPS and summary["motions"] == 2 * NUM_CLIPS
    for sub, ext in (
        ("new_joint_vecs", ".npy"),
        ("new_joints", ".npy"),
        ("texts", ".txt"),
        ("labels", ".json"),
    ):
        assert sorted(p.name[: -len(ext)] for p in (root / sub).iterdir()) == expected, sub
    assert not list(root.parent.glob(".ds.*")), "temporary folders must be gone"
    lengths = []
    for motion_id in expected:
        feats = np.load(root / "new_joint_vecs" / f"{motion_id}.npy")
        joints = np.load(root / "new_joints" / f"{motion_id}.npy")
        label = json.loads((root / "labels" / f"{motion_id}.json").read_text())
        assert feats.dtype == np.float32 and joints.dtype == np.float32
        assert feats.ndim == 2 and feats.shape[1] == 263
        assert joints.shape == (feats.shape[0], 22, 3)
        assert 40 <= feats.shape[0] <= 196
        assert label["fps"] == 20 and label["num_frames"] == feats.shape[0]
        assert np.isfinite(feats).all()
        # new_joints are the joints recovered from the saved features, as in HumanML3D.
        np.testing.assert_allclose(joints, recover_from_ric(feats), atol=1e-6)
        lengths.append(feats.shape[0])
    assert max(lengths) > 120, "composites make clips longer than a single action"
    for name in ("Mean.npy", "Std.npy"):
        arr = np.load(root / name)
        assert arr.shape == (263,) and arr.dtype == np.float32


@pytest.mark.slow
def test_labels_name_actions_and_parameters_as_the_spec(dataset):
    root, summary = dataset
    composites = 0
    counted = {}
    for motion_id in ids_of(root):
        label = json.loads((root / "labels" / f"{motion_id}.json").read_text())
        parts = label["parts"]
        assert 1 <= len(parts) <= 2
        composites += len(parts) == 2 and not motion_id.startswith("M")
        assert parts[0]["start"] == 0 and parts[-1]["end"] == label["num_frames"]
        for a, b in zip(parts[:-1], parts[1:]):
            assert a["end"] == b["start"]
        for p in parts:
            assert p["action"] in PARAMS
            assert set(p["params"]) == set(PARAMS[p["action"]]), p
            for k, v in p["params"].items():
                assert v in PARAMS[p["action"]][k], p
            assert p["end"] - p["start"] >= 40, "each action lasts at least 2 s"
            assert p["end"] - p["start"] <= 120, "each action lasts at most 6 s"
            if not motion_id.startswith("M"):
                counted[p["action"]] = counted.get(p["action"], 0) + 1
    assert counted == summary["actions"]
    assert composites == summary["composites"]
    assert 0.15 * NUM_CLIPS <= composites <= 0.5 * NUM_CLIPS, "about a third of the clips chain two actions"


LINE = re.compile(r"^[^#]+#[^#]+#[0-9.]+#[0-9.]+$")
TOKEN = re.compile(r"^[a-z0-9]+/([A-Z]+)$")


@pytest.mark.slow
def test_caption_lines_parse_and_subspans_point_at_the_parts(dataset):
    root, _ = dataset
    for motion_id in ids_of(root):
        lines = (root / "texts" / f"{motion_id}.txt").read_text().splitlines()
        parts = json.loads((root / "labels" / f"{motion_id}.json").read_text())["parts"]
        whole = [ln for ln in lines if ln.endswith("#0.0#0.0")]
        assert len(whole) == 3, f"{motion_id}: three paraphrased whole-clip captions"
        assert len(set(whole)) == 3
        spans = set()
        for line in lines:
            assert LINE.match(line), line
            text, tokens, start, end = line.split("#")
            assert text == text.lower() and text.strip() == text
            words, toks = text.split(), tokens.split()
            assert len(words) == len(toks), f"every word gets a tag: {line}"
            for tok in toks:
                m = TOKEN.match(tok)
                assert m and m.group(1) in TAGS, tok
            if (start, end) != ("0.0", "0.0"):
                spans.add((int(float(start) * 20), int(float(end) * 20)))
        if len(parts) > 1:
            assert spans == {(p["start"], p["end"]) for p in parts}
        else:
            assert not spans


WORDS = {
    "forward": {"forward", "forwards", "ahead"},
    "backward": {"backward", "backwards", "back"},
    "left": {"left"},
    "right": {"right"},
    "clockwise": {"clockwise"},
    "counterclockwise": {"counterclockwise", "anticlockwise"},
    "slow": {"slowly", "slow", "leisurely", "strolls"},
    "fast": {"quickly", "fast", "briskly", "rapidly", "quick", "brisk", "hurried", "hurries", "strides"},
    1: {"once", "one", "single", "a"},
    2: {"twice", "two", "2"},
    3: {"three", "3", "thrice"},
    180: {"around", "180", "half"},
    "in_place": {"place", "spot", "up"},
}


def test_captions_name_every_label_parameter():
    rng = np.random.default_rng(0)
    for action, params in PARAMS.items():
        combos = [{}]
        for k, values in params.items():
            combos = [dict(c, **{k: v}) for c in combos for v in sorted(values, key=str)]
        for p in combos:
            for _ in range(20):
                for line in clip_captions(
                    rng, [{"action": action, "params": p, "start": 0, "end": 60}], [action == "sit"]
                ):
                    words = set(line.split("#")[0].split())
                    assert words <= set(LEXICON), line
                    for value in p.values():
                        if value in WORDS:
                            assert words & WORDS[value], (p, line)
                    if p.get("angle") == 90:
                        assert not words & WORDS[180], line
                    if p.get("speed") == "normal":
                        assert not words & (WORDS["slow"] | WORDS["fast"]), line


@pytest.mark.slow
def test_mirrors_swap_sides_in_joints_captions_and_labels(dataset):
    root, _ = dataset
    swapped_words = 0
    for motion_id in ids_of(root):
        if motion_id.startswith("M"):
            continue
        mid = "M" + motion_id
        label = json.loads((root / "labels" / f"{motion_id}.json").read_text())
        m_label = json.loads((root / "labels" / f"{mid}.json").read_text())
        assert m_label["num_frames"] == label["num_frames"]
        for p, q in zip(label["parts"], m_label["parts"]):
            assert q["params"] == mirror_params(p["params"])
            assert (q["action"], q["start"], q["end"]) == (p["action"], p["start"], p["end"])
        lines = (root / "texts" / f"{motion_id}.txt").read_text().splitlines()
        m_lines = (root / "texts" / f"{mid}.txt").read_text().splitlines()
        assert m_lines == [mirror_caption_line(ln) for ln in lines]
        for ln, mln in zip(lines, m_lines):
            if " left " in f" {ln.split('#')[0]} ":
                assert " right " in f" {mln.split('#')[0]} "
                swapped_words += 1
        joints = torch.from_numpy(np.load(root / "new_joints" / f"{motion_id}.npy"))
        m_joints = np.load(root / "new_joints" / f"{mid}.npy")
        np.testing.assert_allclose(m_joints, mirror_joints(joints, T2M_SKELETON).numpy(), atol=2e-4)
    assert swapped_words > 0
    assert (
        mirror_caption_line(
            "a man waves his left hand#a/DET man/NOUN wave/VERB his/DET left/ADJ hand/NOUN#0.0#0.0"
        )
        == "a man waves his right hand#a/DET man/NOUN wave/VERB his/DET right/ADJ hand/NOUN#0.0#0.0"
    )
    assert mirror_caption_line("x walks in a clockwise circle#x/X#1.5#3.0").startswith(
        "x walks in a counterclockwise circle#"
    )
    assert mirror_params({"side": "clockwise", "angle": 90}) == {"side": "counterclockwise", "angle": 90}


def test_feature_space_mirror_equals_mirroring_the_joints():
    rng = np.random.default_rng(3)
    for action, params in (
        ("walk", {"direction": "left", "speed": "normal"}),
        ("turn", {"side": "left", "angle": 180}),
        ("kick", {"foot": "right"}),
        ("wave", {"hand": "left"}),
    ):
        world, _ = make_motion([PartSpec(action, params, 70)], rng)
        feats = joints_to_features(torch.from_numpy(world), retarget=False).numpy()
        direct = joints_to_features(
            mirror_joints(torch.from_numpy(world), T2M_SKELETON), retarget=False
        ).numpy()
        np.testing.assert_allclose(gen.mirror_features(feats), direct, atol=1e-9)
        assert not np.allclose(feats, direct, atol=1e-3)


@pytest.mark.slow
def test_splits_are_disjoint_cover_everything_and_keep_mirrors_together(dataset):
    root, summary = dataset
    split = {name: ids_of(root, name) for name in ("train", "val", "test", "train_val", "all")}
    train, val, test = (set(split[k]) for k in ("train", "val", "test"))
    assert not (train & val) and not (train & test) and not (val & test)
    assert train | val | test == set(split["all"]) and len(split["all"]) == 2 * NUM_CLIPS
    assert set(split["train_val"]) == train | val
    for ids in (train, val, test):
        assert all(("M" + i in ids) for i in ids if not i.startswith("M"))
        assert all((i[1:] in ids) for i in ids if i.startswith("M"))
    assert (len(train), len(val), len(test)) == (96, 6, 18)  # 80/5/15 of 60 clips, times two
    assert summary["splits"] == {"train": 96, "val": 6, "test": 18}


@pytest.mark.slow
def test_mean_std_are_the_reference_statistics_of_all_files(dataset):
    root, _ = dataset
    stacked = np.concatenate([np.load(p) for p in sorted((root / "new_joint_vecs").glob("*.npy"))])
    mean, std = reference_std(stacked.astype(np.float64), 22)
    np.testing.assert_allclose(np.load(root / "Mean.npy"), mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.load(root / "Std.npy"), std, rtol=1e-5, atol=1e-6)
    saved = np.load(root / "Std.npy")
    for group in FeatureLayout(22).groups():
        assert np.all(saved[group] == saved[group][0]), "Std is constant inside each group"
    assert (saved > 0).all()


@pytest.mark.slow
def test_same_seed_gives_identical_bytes_in_worker_processes_and_another_seed_differs(
    dataset, tmp_path, monkeypatch
):
    root, _ = dataset
    again = tmp_path / "again"
    monkeypatch.setattr(gen, "POOL_MIN_CHUNKS", 1)  # NUM_CLIPS are 2 chunks: drawn by 2 processes
    spawned = []
    context = gen.multiprocessing.get_context

    def spawn_context(method):
        spawned.append(method)
        return context(method)

    monkeypatch.setattr(gen.multiprocessing, "get_context", spawn_context)
    gen.generate_dataset(again, num_clips=NUM_CLIPS, seed=SEED, progress=False, workers=2)
    assert spawned == ["spawn"]
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        assert (root / rel).read_bytes() == (again / rel).read_bytes(), rel
    # One clip alone equals its copy in the dataset: each clip has its own random stream.
    clip = gen.generate_clip(SEED, 5)
    np.testing.assert_array_equal(clip.features, np.load(root / "new_joint_vecs" / "000005.npy"))
    other = gen.generate_clip(SEED + 1, 5)
    assert other.features.shape != clip.features.shape or not np.array_equal(other.features, clip.features)


def test_refuses_to_overwrite_and_replaces_atomically(tmp_path):
    out = tmp_path / "data"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match=r"data.*not empty.*overwrite=True"):
        gen.generate_dataset(out, num_clips=3, seed=0, progress=False)
    assert (out / "keep.txt").read_text() == "mine"
    # overwrite replaces only a dataset this generator made, never a folder of someone's own files
    with pytest.raises(FileExistsError, match=r"data holds files but no synthetic dataset \(no synthesis"):
        gen.generate_dataset(out, num_clips=3, seed=0, progress=False, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    (out / "keep.txt").unlink()
    gen.generate_dataset(out, num_clips=2, seed=1, progress=False)
    summary = gen.generate_dataset(out, num_clips=3, seed=0, progress=False, overwrite=True)
    assert summary["clips"] == 3 and json.loads((out / "synthesis.json").read_text())["seed"] == 0
    assert (out / "all.txt").read_text().split() == [
        "000000",
        "000001",
        "000002",
        "M000000",
        "M000001",
        "M000002",
    ]
    assert all((out / f"{s}.txt").read_text().split() for s in ("train", "val", "test"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"], "no temporary folder left"
    (tmp_path / "empty").mkdir()
    gen.generate_dataset(tmp_path / "empty", num_clips=2, seed=0, progress=False)  # an empty folder is fine


def test_a_crash_leaves_no_half_written_dataset(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = gen._generate_chunk

    def failing(seed, indices, *a, **k):
        calls["n"] += 1
        if calls["n"] > 1:
            raise RuntimeError("simulated crash")
        return real(seed, indices, *a, **k)

    monkeypatch.setattr(gen, "CHUNK", 2)
    monkeypatch.setattr(gen, "_generate_chunk", failing)
    with pytest.raises(RuntimeError, match="simulated crash"):
        gen.generate_dataset(tmp_path / "ds", num_clips=5, seed=0, progress=False)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_feet_do_not_slide_while_in_contact(dataset):
    """Horizontal speed of the foot joints on frames whose contact label is 1 (measured on the
    default dataset: toes median 0.000 m/s, 90th percentile 0.015 m/s; ankles 0.000 / 0.09 m/s,
    the ankle legitimately rolls over the planted toe at heel-off)."""
    root, _ = dataset
    speeds = {7: [], 10: [], 8: [], 11: []}
    for motion_id in ids_of(root):
        feats = np.load(root / "new_joint_vecs" / f"{motion_id}.npy")
        joints = np.load(root / "new_joints" / f"{motion_id}.npy")
        contact = feats[:-1, -4:] > 0.5
        for k, j in enumerate((7, 10, 8, 11)):
            v = np.linalg.norm(np.diff(joints[:, j, [0, 2]], axis=0), axis=1) * 20
            speeds[j].append(v[contact[:, k]])
    for j, chunks in speeds.items():
        v = np.concatenate(chunks)
        assert len(v) > 1000
        assert np.median(v) < 0.005, (j, np.median(v))
        assert np.percentile(v, 90) < (0.04 if j in (10, 11) else 0.15), (j, np.percentile(v, 90))
    toes = np.concatenate(speeds[10] + speeds[11])
    assert np.mean(toes < 0.01) > 0.85


@pytest.mark.slow
def test_statistics_resemble_real_humanml3d(dataset, reference_dir):
    """Mean/Std against ../shared/reference/humanml3d (measured on the default 1,500 clips: root
    height mean 0.82 vs 0.94, contacts 0.82 vs 0.85, group stds 0.67-2.1x the real ones)."""
    root, _ = dataset
    mean, std = np.load(root / "Mean.npy"), np.load(root / "Std.npy")
    real_mean = np.load(reference_dir / "humanml3d" / "Mean.npy")
    real_std = np.load(reference_dir / "humanml3d" / "Std.npy")
    assert abs(real_mean[3] - 0.94) < 0.01
    assert abs(mean[3] - real_mean[3]) < 0.16, ("root height", mean[3], real_mean[3])
    assert np.all(np.abs(mean[-4:] - real_mean[-4:]) < 0.12), ("contacts", mean[-4:], real_mean[-4:])
    for name, group in zip(
        ("yaw", "root velocity", "height", "positions", "rotations", "velocities", "contacts"),
        FeatureLayout(22).groups(),
    ):
        ratio = std[group][0] / real_std[group][0]
        assert 0.4 < ratio < 3.0, (name, ratio)
    # Forward root velocity is positive on average (people mostly walk forwards), as in the real data.
    assert mean[2] > 0 and real_mean[2] > 0


@pytest.mark.slow
def test_extra_train_paraphrases_leave_motions_and_held_out_splits_as_the_default(dataset, tmp_path):
    root, _ = dataset
    more = tmp_path / "more"
    summary = gen.generate_dataset(more, num_clips=NUM_CLIPS, seed=SEED, progress=False, train_paraphrases=8)
    assert summary["train_paraphrases"] == 8
    assert json.loads((more / "synthesis.json").read_text()) == {
        "num_clips": NUM_CLIPS,
        "seed": SEED,
        "train_paraphrases": 8,
        "extra_train_clips": 0,
        "extra_composite_fraction": gen.COMPOSITE_FRACTION,
    }
    train = set(ids_of(root, "train"))
    whole_counts = []
    for motion_id in ids_of(root):
        for sub in ("new_joint_vecs", "new_joints"):
            assert (more / sub / f"{motion_id}.npy").read_bytes() == (
                root / sub / f"{motion_id}.npy"
            ).read_bytes()
        old = (root / "texts" / f"{motion_id}.txt").read_text().splitlines()
        new = (more / "texts" / f"{motion_id}.txt").read_text().splitlines()
        if motion_id not in train:
            assert new == old, motion_id  # val and test captions are the default's
            continue
        assert new[: len(old)] == old, motion_id  # the clip's own lines first, unchanged
        added = new[len(old) :]
        assert all(line.endswith("#0.0#0.0") for line in added), "extra lines describe the whole clip"
        whole = [line for line in new if line.endswith("#0.0#0.0")]
        assert len(set(whole)) == len(whole), f"{motion_id}: a paraphrase repeats"
        whole_counts.append(len(whole))
        label = json.loads((more / "labels" / f"{motion_id}.json").read_text())
        assert len(label["parts"]) >= 1
    # Templates may run out for a simple clip ("stands still"); the summary counts the shortfall.
    assert max(whole_counts) == 8
    assert summary["paraphrases_short"] == sum(8 - n for n in whole_counts) // 2  # mirrors too
    # The mirror's extra lines are the mirrored extra lines.
    mid = next(i for i in sorted(train) if not i.startswith("M"))
    lines = (more / "texts" / f"{mid}.txt").read_text().splitlines()
    mirrored = (more / "texts" / f"M{mid}.txt").read_text().splitlines()
    assert mirrored == [mirror_caption_line(line) for line in lines]


@pytest.mark.slow
def test_extra_train_clips_add_training_clips_and_leave_the_held_out_splits_alone(dataset, tmp_path):
    root, _ = dataset
    more = tmp_path / "more"
    summary = gen.generate_dataset(more, num_clips=NUM_CLIPS, seed=SEED, progress=False, extra_train_clips=5)
    assert summary["clips"] == NUM_CLIPS + 5 and summary["extra_train_clips"] == 5
    assert json.loads((more / "synthesis.json").read_text())["extra_train_clips"] == 5
    extra = [f"{i:06d}" for i in range(NUM_CLIPS, NUM_CLIPS + 5)]
    for split in ("val", "test"):
        assert ids_of(more, split) == ids_of(root, split)
    assert ids_of(more, "train") == sorted(ids_of(root, "train") + extra + ["M" + i for i in extra])
    assert summary["splits"]["train"] == len(ids_of(root, "train")) + 10
    # The default's clips are byte for byte the same; the extra ones are the clips a larger
    # dataset draws at those indices (each clip has its own stream).
    for motion_id in ids_of(root):
        for name in (f"new_joint_vecs/{motion_id}.npy", f"texts/{motion_id}.txt", f"labels/{motion_id}.json"):
            assert (more / name).read_bytes() == (root / name).read_bytes(), name
    alone = gen.generate_clip(SEED, NUM_CLIPS + 2)
    np.testing.assert_array_equal(np.load(more / "new_joint_vecs" / f"{extra[2]}.npy"), alone.features)
    # The statistics include the extra clips.
    assert not np.array_equal(np.load(more / "Mean.npy"), np.load(root / "Mean.npy"))
    with pytest.raises(ValueError, match=r"extra_train_clips 5 \(asked 0\)"):
        gen.check_synthesis(more, NUM_CLIPS, SEED, 3)
    gen.check_synthesis(more, NUM_CLIPS, SEED, 3, extra_train_clips=5)
    with pytest.raises(ValueError, match="extra_train_clips must be >= 0"):
        gen.generate_dataset(tmp_path / "x", num_clips=3, seed=0, progress=False, extra_train_clips=-1)
    with pytest.raises(ValueError, match="workers must be >= 1, got 0"):
        gen.generate_dataset(tmp_path / "x", num_clips=3, seed=0, progress=False, workers=0)
    # Refused before a list of ten billion clips is made (a MemoryError before), naming the disk.
    with pytest.raises(ValueError, match=r"10000000005 clips need about 5,400,000.0 GB on disk .* GB free"):
        gen.generate_dataset(tmp_path / "huge", num_clips=5, seed=0, progress=False, extra_train_clips=10**10)
    assert not (tmp_path / "huge").exists()


@pytest.mark.slow
def test_extra_composite_fraction_sets_the_share_of_two_action_extra_clips_only(dataset, tmp_path):
    root, _ = dataset
    n_extra = 6
    extra = [f"{i:06d}" for i in range(NUM_CLIPS, NUM_CLIPS + n_extra)]
    parts = {}
    for fraction in (0.0, 1.0):
        out = tmp_path / f"c{fraction}"
        summary = gen.generate_dataset(
            out,
            num_clips=NUM_CLIPS,
            seed=SEED,
            progress=False,
            extra_train_clips=n_extra,
            extra_composite_fraction=fraction,
        )
        assert summary["extra_composite_fraction"] == fraction
        assert json.loads((out / "synthesis.json").read_text())["extra_composite_fraction"] == fraction
        for motion_id in ids_of(root):  # the first NUM_CLIPS clips are the default's, byte for byte
            for name in (f"new_joint_vecs/{motion_id}.npy", f"labels/{motion_id}.json"):
                assert (out / name).read_bytes() == (root / name).read_bytes(), name
        parts[fraction] = [
            len(json.loads((out / "labels" / f"{i}.json").read_text())["parts"]) for i in extra
        ]
        gen.check_synthesis(out, NUM_CLIPS, SEED, 3, n_extra, fraction)
        with pytest.raises(ValueError, match=rf"extra_composite_fraction {fraction} \(asked 0.5\)"):
            gen.check_synthesis(out, NUM_CLIPS, SEED, 3, n_extra, 0.5)
    assert parts == {0.0: [1] * n_extra, 1.0: [2] * n_extra}
    with pytest.raises(ValueError, match=r"extra_composite_fraction must be within \[0, 1\], got 1.5"):
        gen.generate_dataset(
            tmp_path / "x", num_clips=3, seed=0, progress=False, extra_composite_fraction=1.5
        )


def test_a_synthetic_folder_made_with_other_settings_is_refused(tmp_path):
    gen.generate_dataset(tmp_path / "ds", num_clips=3, seed=0, progress=False)
    gen.check_synthesis(tmp_path / "ds", 3, 0, 3)  # the same settings: accepted
    made = tmp_path / "ds" / "synthesis.json"
    made.write_text(
        json.dumps(
            {
                k: v
                for k, v in json.loads(made.read_text()).items()
                if k not in ("extra_train_clips", "extra_composite_fraction")
            }
        )
    )
    gen.check_synthesis(tmp_path / "ds", 3, 0, 3)  # written before the extra options existed: defaults
    from mmm.data.configs import DataConfig, SynthConfig
    from mmm.data.datamodule import TokenizerDataModule

    asked = SynthConfig(num_clips=3, seed=0, train_paraphrases=12)
    with pytest.raises(ValueError, match="train_paraphrases 3 \\(asked 12\\)"):  # training refuses it too
        TokenizerDataModule(DataConfig(root=str(tmp_path / "ds"), synthesize=asked)).prepare_data()
    with pytest.raises(
        ValueError, match=r"ds: synthetic dataset made with train_paraphrases 3 \(asked 12\).*another"
    ):
        gen.check_synthesis(tmp_path / "ds", 3, 0, 12)
    with pytest.raises(ValueError, match=r"num_clips 3 \(asked 1500\), seed 0 \(asked 1\)"):
        gen.check_synthesis(tmp_path / "ds", 1500, 1, 3)
    with pytest.raises(ValueError, match="train_paraphrases must be >= 3"):
        gen.generate_dataset(tmp_path / "x", num_clips=3, seed=0, progress=False, train_paraphrases=2)

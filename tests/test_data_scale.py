"""The feature pack (one memory-mapped file instead of one .npy per motion) and the loaders that
stay lean at scale: same arrays as file-by-file loading, rebuilt when stale, never half-written,
the same errors, streaming statistics and windows normalized when drawn."""

import json
import logging
import time

import numpy as np
import pytest

from mmm.data import humanml3d as h
from mmm.data.datasets import MotionWindowDataset, normalize
from mmm.data.humanml3d import (
    Caption,
    CaptionStore,
    DataError,
    FeatureStore,
    compute_stats,
    load_clips,
    load_items,
)
from mmm.motion.features import reference_std
from tests.helpers import D, write_dataset

WHOLE = "a person walks forward#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0"
SPAN = "then jumps#then/ADV jump/VERB#2.0#5.5"


@pytest.fixture
def settled(monkeypatch):
    """Files written by the test count as settled at once (the pack waits PACK_SETTLE_S otherwise)."""
    monkeypatch.setattr(h, "PACK_SETTLE_S", 0.0)


def _dataset(root, n=6):
    clips = {f"{i:06d}": (60 + 13 * i, [WHOLE, SPAN] if i % 2 else [WHOLE]) for i in range(n)}
    ids = list(clips)
    return write_dataset(root, clips, {"train": ids[:-2], "val": ids[-2:], "test": ids[-1:]})


def _packs(root):
    folder = root / h.PACK_DIR
    return sorted(p.name for p in folder.iterdir() if p.is_dir()) if folder.exists() else []


def test_packed_loading_gives_the_same_arrays_as_file_by_file(tmp_path, settled):
    arrays = _dataset(tmp_path)
    items, report = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    assert len(_packs(tmp_path)) == 1
    store = FeatureStore(tmp_path, D)
    assert store.packed and not store.built  # the load above built it; this one reads it
    unpacked = FeatureStore(tmp_path, D, pack=False)
    assert not unpacked.packed
    for motion_id, arr in arrays.items():
        packed = store.load(motion_id)
        assert packed.dtype == np.float32 and packed.shape == arr.shape
        assert packed.tobytes() == unpacked.load(motion_id).tobytes() == arr.tobytes()
        assert not packed.flags.writeable  # a view of the read-only memory map, not a copy
    for item in items:
        whole = arrays[item.motion_id]
        assert item.features.tobytes() == whole[item.start : item.start + item.length].tobytes()
    clips, _ = load_clips(tmp_path, "val", feature_dim=D, min_length=40)
    assert all(clips[k].tobytes() == arrays[k].tobytes() for k in clips)
    assert report.kept_clips == 4


def test_a_changed_file_makes_a_new_pack_and_the_stale_one_goes(tmp_path, settled):
    _dataset(tmp_path)
    FeatureStore(tmp_path, D)
    (old,) = _packs(tmp_path)
    new = np.full((70, D), 3.0, np.float32)
    np.save(tmp_path / "new_joint_vecs/000001.npy", new)  # another shape
    store = FeatureStore(tmp_path, D)
    assert store.built and _packs(tmp_path) == [store.folder.name] != [old]
    assert store.load("000001").tobytes() == new.tobytes()
    # The same size rewritten in place: the ctime tells it apart (once the clock has ticked, which
    # PACK_SETTLE_S waits for outside tests).
    time.sleep(0.05)
    same_size = np.full((70, D), 4.0, np.float32)
    np.save(tmp_path / "new_joint_vecs/000001.npy", same_size)
    assert FeatureStore(tmp_path, D).load("000001").tobytes() == same_size.tobytes()
    # A removed file: the pack no longer has it, and loading it names the missing file.
    (tmp_path / "new_joint_vecs/000001.npy").unlink()
    with pytest.raises(DataError, match=r"000001\.npy: motion file is missing"):
        FeatureStore(tmp_path, D).load("000001")
    assert len(_packs(tmp_path)) == 1


def test_a_crash_while_packing_leaves_no_pack_and_the_next_load_builds_it(tmp_path, settled, monkeypatch):
    arrays = _dataset(tmp_path)
    real = h.load_motion
    calls = []

    def crash_on_third(path, feature_dim):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt  # what a Ctrl-C halfway through looks like
        return real(path, feature_dim)

    monkeypatch.setattr(h, "load_motion", crash_on_third)
    with pytest.raises(KeyboardInterrupt):
        FeatureStore(tmp_path, D)
    assert _packs(tmp_path) == []  # neither a pack nor its temporary folder
    monkeypatch.setattr(h, "load_motion", real)
    # A SIGKILLed writer's temporary folder (its process is gone) is cleaned by the next build.
    (tmp_path / h.PACK_DIR / ".tmp-0123456789abcdef-999999999").mkdir()
    store = FeatureStore(tmp_path, D)
    assert store.built and _packs(tmp_path) == [store.folder.name]
    assert store.load("000004").tobytes() == arrays["000004"].tobytes()


def test_a_damaged_pack_is_not_used(tmp_path, settled, caplog):
    arrays = _dataset(tmp_path)
    store = FeatureStore(tmp_path, D)
    with open(store.folder / "features.f32", "r+b") as fh:
        fh.truncate(100)
    with caplog.at_level(logging.WARNING):
        again = FeatureStore(tmp_path, D)
    assert not again.packed and "unusable feature pack" in caplog.text
    assert again.load("000002").tobytes() == arrays["000002"].tobytes()


@pytest.mark.parametrize(
    "breakage, message",
    [
        (
            lambda r: (r / "new_joint_vecs/000001.npy").write_bytes(b"garbage"),
            r"000001\.npy: unreadable \.npy",
        ),
        (
            lambda r: np.save(r / "new_joint_vecs/000001.npy", np.zeros((80, 251), np.float32)),
            r"000001\.npy: wrong feature shape \(T, 251\), expected \(T, 263\); 251-d features are KIT-ML",
        ),
        (
            lambda r: np.save(r / "new_joint_vecs/000001.npy", np.full((80, D), np.nan, np.float32)),
            r"000001\.npy: NaN/Inf values \(80 of 80",
        ),
    ],
)
def test_bad_files_in_a_pack_raise_what_file_by_file_loading_raises(tmp_path, settled, breakage, message):
    _dataset(tmp_path)
    breakage(tmp_path)
    store = FeatureStore(tmp_path, D)
    assert store.packed  # the bad file is recorded in the pack, the good ones packed
    with pytest.raises(DataError, match=message) as packed:
        store.load("000001")
    with pytest.raises(DataError) as unpacked:
        FeatureStore(tmp_path, D, pack=False).load("000001")
    assert str(packed.value) == str(unpacked.value)
    with pytest.raises(DataError, match=message) as info:
        load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    assert "data.on_invalid=skip" in str(info.value)
    items, report = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40, on_invalid="skip")
    assert "000001" not in {i.motion_id for i in items} and sum(report.skipped.values()) == 1


def test_fresh_files_and_unwritable_datasets_are_read_file_by_file(tmp_path, monkeypatch, caplog):
    arrays = _dataset(tmp_path)
    store = FeatureStore(tmp_path, D)  # just written: not settled, not packed yet
    assert not store.packed and _packs(tmp_path) == []
    assert store.load("000003").tobytes() == arrays["000003"].tobytes()
    monkeypatch.setattr(h, "PACK_SETTLE_S", 0.0)

    def refuse(*args):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(h, "_write_pack", refuse)
    with caplog.at_level(logging.WARNING):
        store = FeatureStore(tmp_path, D)
        items, _ = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    assert not store.packed and caplog.text.count("cannot pack the features") == 1
    assert {i.motion_id for i in items} == {"000000", "000001", "000002", "000003"}


def test_the_pack_is_one_file_and_an_index(tmp_path, settled):
    arrays = _dataset(tmp_path, n=3)
    store = FeatureStore(tmp_path, D)
    index = json.loads((store.folder / "index.json").read_text())
    assert index["ids"] == sorted(arrays) and index["frames"] == sum(len(a) for a in arrays.values())
    assert (store.folder / "features.f32").stat().st_size == index["frames"] * D * 4


def _captions_of(items):
    return {(i.name, c) for i in items for c in i.captions}


def test_packed_captions_are_the_captions_of_the_files_and_follow_changes(tmp_path, settled):
    _dataset(tmp_path)
    (tmp_path / "texts/000002.txt").write_text(f"{WHOLE}\nnan spans#a/DET#nan#nan\n")
    unpacked, _ = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    store = CaptionStore(tmp_path)
    assert store.packed and store.folder.parent.name == h.CAPTION_PACK_DIR
    for motion_id in ("000000", "000001", "000002"):
        assert store.load(motion_id) == h.read_captions(tmp_path / "texts" / f"{motion_id}.txt")
    assert store.load("000002")[1] == Caption("nan spans", ("a/DET",), 0.0, 0.0)
    # load_items packed it on its first call; both calls give the same items and captions.
    packed, _ = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    assert [i.name for i in packed] == [i.name for i in unpacked] and len(packed) == 5
    assert _captions_of(packed) == _captions_of(unpacked)
    # An edited caption file: a new pack with the new text, the stale pack removed.
    old = store.folder.name
    (tmp_path / "texts/000003.txt").write_text("a person waves#a/DET person/NOUN wave/VERB#0.0#0.0\n")
    again = CaptionStore(tmp_path)
    assert again.folder.name != old and not (tmp_path / h.CAPTION_PACK_DIR / old).exists()
    assert [c.text for c in again.load("000003")] == ["a person waves"]


def test_bad_caption_files_in_a_pack_raise_what_file_by_file_reading_raises(tmp_path, settled):
    _dataset(tmp_path)
    (tmp_path / "texts/000001.txt").write_text(f"{WHOLE}\nno fields here\n")
    (tmp_path / "texts/000003.txt").write_text("")
    (tmp_path / "texts/000002.txt").unlink()
    store = CaptionStore(tmp_path)
    assert store.packed
    for motion_id, message in [
        ("000001", r"texts/000001\.txt:2: malformed caption line \(1 '#'-separated fields"),
        ("000003", r"texts/000003\.txt: caption file is empty"),
        ("000002", r"texts/000002\.txt: caption file is missing"),
    ]:
        with pytest.raises(DataError, match=message) as packed:
            store.load(motion_id)
        with pytest.raises(DataError) as unpacked:
            CaptionStore(tmp_path, pack=False).load(motion_id)
        assert str(packed.value) == str(unpacked.value)
    items, report = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40, on_invalid="skip")
    assert sum(report.skipped.values()) == 3 and {i.motion_id for i in items} == {"000000"}
    # The dataset folder moved: the errors name the files where they are now.
    moved = tmp_path.parent / f"{tmp_path.name}-moved"
    tmp_path.rename(moved)
    with pytest.raises(DataError, match=f"{moved}/texts/000001\\.txt:2: malformed") as info:
        CaptionStore(moved).load("000001")
    assert CaptionStore(moved).packed and str(tmp_path) + "/" not in str(info.value)


def test_streaming_statistics_match_the_reference_on_all_frames(tmp_path, settled, monkeypatch):
    arrays = _dataset(tmp_path, n=5)
    stacked = np.concatenate(list(arrays.values())).astype(np.float64)
    ref_mean, ref_std = reference_std(stacked, 22)
    for block_frames in (1 << 16, 50):  # one block, and many blocks
        monkeypatch.setattr(
            FeatureStore, "blocks", lambda self, ids, b=block_frames, f=FeatureStore.blocks: f(self, ids, b)
        )
        mean, std, report = compute_stats(tmp_path, 22)
        np.testing.assert_allclose(mean, ref_mean.astype(np.float32), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(std, ref_std.astype(np.float32), rtol=1e-6)
        assert report.kept_clips == 5


def test_windows_normalized_when_drawn_equal_normalizing_whole_motions(tmp_path):
    rng = np.random.default_rng(0)
    motions = [rng.normal(size=(T, D)).astype(np.float32) for T in (64, 80, 30, 100)]
    mean = rng.normal(size=D).astype(np.float32)
    std = rng.uniform(0.5, 2, size=D).astype(np.float32)
    ds = MotionWindowDataset(motions, mean, std, window=64)
    expected = [normalize(m, mean, std) for m in motions if len(m) >= 64]
    windows = [w[o : o + 64] for w in expected for o in range(len(w) - 63)]
    assert len(ds) == len(windows) and ds.num_too_short == 1
    for i, w in enumerate(windows):
        assert ds[i].numpy().tobytes() == w.tobytes()

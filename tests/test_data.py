"""The on-disk reader, its length rules and errors, the datasets and the datamodules."""

import logging
import re
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from mmm.config import ConfigError, compose, conf_dir, to_object
from mmm.data.configs import DataConfig, OversampleConfig
from mmm.data.datamodule import TextMotionDataModule, TokenizerDataModule, oversample_items
from mmm.data.datasets import MotionWindowDataset, TextMotionDataset, collate_motions
from mmm.data.humanml3d import (
    DataError,
    check_mirror_splits,
    compute_stats,
    load_clips,
    load_items,
    load_stats,
    mirror_id,
    parse_caption_line,
    read_captions,
)
from tests.helpers import D, make_features, write_dataset

WHOLE = "a person walks forward#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0"


def test_parse_caption_line():
    c = parse_caption_line("a man jumps#a/DET man/NOUN jump/VERB#1.5#4.0")
    assert (c.text, c.tokens, c.start, c.end, c.whole_clip) == (
        "a man jumps",
        ("a/DET", "man/NOUN", "jump/VERB"),
        1.5,
        4.0,
        False,
    )
    assert parse_caption_line("x#x/NOUN#nan#nan").whole_clip
    with pytest.raises(DataError, match=r"t\.txt:3: malformed caption line \(2"):
        parse_caption_line("no tokens#0.0", "t.txt", 3)
    with pytest.raises(DataError, match="empty caption text"):
        parse_caption_line("#a/DET#0.0#0.0", "t.txt", 1)
    with pytest.raises(DataError, match="empty caption line"):
        parse_caption_line("   ", "t.txt", 2)
    # A '#' inside the caption is text (the four fields are split from the right).
    assert parse_caption_line("jumps #2 of 3#jump/VERB#0.0#0.0").text == "jumps #2 of 3"
    with pytest.raises(DataError, match="not numbers"):
        parse_caption_line("x#x/NOUN#a#b", "t.txt", 1)
    with pytest.raises(DataError, match="empty or negative"):
        parse_caption_line("x#x/NOUN#3.0#2.0", "t.txt", 1)


def test_blank_caption_lines_are_passed_over_and_errors_keep_their_line_numbers(tmp_path):
    path = tmp_path / "000000.txt"
    path.write_bytes(
        b"a man walks#a/DET man/NOUN walk/VERB#0.0#0.0\r\n\r\n  \na man jumps#x/NOUN#0.0#0.0\n\n\n"
    )
    assert [c.text for c in read_captions(path)] == ["a man walks", "a man jumps"]
    path.write_text("a man walks#a/DET#0.0#0.0\n\nbroken\n\n")
    with pytest.raises(DataError, match=r"000000\.txt:3: malformed caption line"):
        read_captions(path)
    path.write_text("\n \n")
    with pytest.raises(DataError, match="caption file is empty"):
        read_captions(path)


def test_mirror_id():
    assert mirror_id("000123") == "M000123" and mirror_id("M000123") == "000123"


def test_load_items_length_rules_and_sub_spans(tmp_path):
    clips = {
        "000000": (
            120,
            [WHOLE, "then jumps#then/ADV jump/VERB#2.0#5.5", "short part#short/ADJ part/NOUN#0.0#1.0"],
        ),
        "000001": (30, [WHOLE]),  # too short
        "000002": (210, [WHOLE]),  # too long (>= 200)
        "000003": (150, ["only a part#only/ADV a/DET part/NOUN#1.0#4.0"]),  # no whole-clip caption
        "000004": (199, [WHOLE]),  # the longest kept
    }
    arrays = write_dataset(tmp_path, clips, {"train": list(clips)})
    items, report = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    names = sorted(i.name for i in items)
    assert names == ["000000", "000000#40-110", "000003#20-80", "000004"]
    span = next(i for i in items if i.name == "000000#40-110")
    assert span.length == 70 and np.array_equal(span.features, arrays["000000"][40:110])
    assert [c.text for c in span.captions] == ["then jumps"]
    whole = next(i for i in items if i.name == "000000")
    assert [c.text for c in whole.captions] == ["a person walks forward"]
    assert report.kept_clips == 3 and report.kept_items == 4
    assert report.skipped["clip length outside [40, 200) frames"] == 2
    assert report.skipped["caption sub-span length outside [40, 200) frames"] == 1
    assert "left out 2: clip length outside" in report.summary()


@pytest.mark.parametrize(
    "breakage, message",
    [
        (lambda r: (r / "new_joint_vecs/000001.npy").unlink(), r"000001\.npy: motion file is missing"),
        (
            lambda r: (r / "new_joint_vecs/000001.npy").write_bytes(b"garbage"),
            r"000001\.npy: unreadable \.npy",
        ),
        (
            lambda r: np.save(r / "new_joint_vecs/000001.npy", np.zeros((80, 251), np.float32)),
            r"000001\.npy: wrong feature shape \(T, 251\), expected \(T, 263\); 251-d features are KIT-ML",
        ),
        (
            lambda r: np.save(r / "new_joint_vecs/000001.npy", np.full((80, 263), np.nan, np.float32)),
            r"000001\.npy: NaN/Inf values \(80 of 80",
        ),
        (
            lambda r: (r / "texts/000001.txt").write_text("broken line\n"),
            r"000001\.txt:1: malformed caption line",
        ),
        (
            lambda r: (r / "texts/000001.txt").write_text(WHOLE + "\n#x/NOUN#0.0#0.0\n"),
            r"000001\.txt:2: empty caption text",
        ),
        (
            lambda r: (r / "train.txt").write_text("000000\n000001\n000009\n"),
            r"000009\.npy: motion file is missing",
        ),
    ],
)
def test_bad_input_is_an_error_naming_the_file_or_a_counted_skip(tmp_path, breakage, message):
    write_dataset(
        tmp_path, {"000000": (80, [WHOLE]), "000001": (80, [WHOLE])}, {"train": ["000000", "000001"]}
    )
    breakage(tmp_path)
    with pytest.raises(DataError, match=message) as info:
        load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    assert "data.on_invalid=skip" in str(info.value)
    items, report = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40, on_invalid="skip")
    kept = ["000000", "000001"] if "000009" in message else ["000000"]
    assert [i.name for i in items] == kept
    assert sum(report.skipped.values()) == 1
    assert len(report.examples) == 1


def test_a_byte_order_mark_is_not_text_and_a_repeated_id_is_kept_once_and_counted(tmp_path):
    write_dataset(
        tmp_path, {"000000": (80, [WHOLE]), "000001": (80, [WHOLE])}, {"train": ["000000", "000001"]}
    )
    # Files saved by editors that write UTF-8 with a byte-order mark (Windows Notepad, Excel)
    (tmp_path / "train.txt").write_text("000000\r\n000001\r\n000000\r\n", encoding="utf-8-sig")
    (tmp_path / "texts/000001.txt").write_text(WHOLE + "\n", encoding="utf-8-sig")
    items, report = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    assert [i.name for i in items] == ["000000", "000001"]
    assert [c.text for c in items[1].captions] == ["a person walks forward"]
    assert report.kept_clips == 2 and report.skipped == {"id listed again in the split (kept once)": 1}
    assert "left out 1: id listed again in the split (kept once) (e.g. 000000)" in report.summary()
    clips, report = load_clips(tmp_path, "train", feature_dim=D, min_length=40)
    assert sorted(clips) == ["000000", "000001"] and report.kept_clips == 2
    assert sum(report.skipped.values()) == 1


def test_missing_split_and_stats_errors(tmp_path):
    write_dataset(tmp_path, {"000000": (80, [WHOLE])}, {"train": ["000000"]}, stats=False)
    with pytest.raises(DataError, match=r"val\.txt: split file is missing"):
        load_items(tmp_path, "val", feature_dim=D, fps=20, min_length=40)
    with pytest.raises(
        DataError, match=r"Mean\.npy: normalization statistics are missing; create them with `mmm data stats"
    ):
        load_stats(tmp_path, D)


def test_split_ids_written_with_an_extension_are_refused_with_the_fix(tmp_path):
    write_dataset(tmp_path, {"000000": (80, [WHOLE])}, {"train": ["000000", "000001.npy", "M000002.NPY"]})
    with pytest.raises(DataError) as err:
        load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40, on_invalid="skip")
    assert str(err.value) == (
        f"{tmp_path / 'train.txt'}: 2 of 3 ids end in a file extension (e.g. 000001.npy, M000002.NPY); "
        "write the ids without .npy/.txt, one per line (000001, not 000001.npy)"
    )


def test_compute_stats_the_reference_way_skips_nan_files(tmp_path):
    arrays = write_dataset(
        tmp_path, {"000000": (50, [WHOLE]), "000001": (70, [WHOLE])}, {"train": ["000000", "000001"]}
    )
    np.save(tmp_path / "new_joint_vecs/000002.npy", np.full((60, D), np.nan, np.float32))
    mean, std, report = compute_stats(tmp_path, 22)
    stacked = np.concatenate([arrays["000000"], arrays["000001"]]).astype(np.float64)
    assert np.allclose(mean, stacked.mean(0), atol=1e-6)
    # Group-averaged std: dims 4..66 share the mean of their per-dim stds.
    assert np.allclose(std[4:67], stacked.std(0)[4:67].mean(), atol=1e-6)
    assert std[0] == pytest.approx(stacked.std(0)[0], rel=1e-6)
    assert report.kept_clips == 2 and sum(report.skipped.values()) == 1


def test_reference_stats_are_group_averaged(reference_dir):
    std = np.load(reference_dir / "humanml3d/Std.npy")
    for a, b in [(1, 3), (4, 67), (67, 193), (193, 259), (259, 263)]:
        assert np.allclose(std[a:b], std[a], rtol=1e-6)


def test_mirror_split_leaks_are_found(tmp_path):
    write_dataset(
        tmp_path,
        {i: (50, [WHOLE]) for i in ["000000", "M000000", "000001", "M000001"]},
        {"train": ["000000", "M000000", "000001"], "test": ["M000001"]},
    )
    assert check_mirror_splits(tmp_path) == ["000001", "M000001"]


def test_window_dataset_enumerates_every_window():
    motions = [make_features(70, 0), make_features(64, 1), make_features(30, 2)]
    mean, std = np.zeros(D, np.float32), np.full(D, 2.0, np.float32)
    ds = MotionWindowDataset(motions, mean, std, window=64)
    assert ds.num_too_short == 1
    assert len(ds) == (70 - 64 + 1) + 1
    assert torch.allclose(ds[0], torch.from_numpy(motions[0][:64] / 2))
    assert torch.allclose(ds[6], torch.from_numpy(motions[0][6:70] / 2))
    assert torch.allclose(ds[7], torch.from_numpy(motions[1] / 2))
    assert torch.equal(ds[8], ds[0])  # indices tagged with the epoch wrap around


def test_window_dataset_switches_its_extra_share_to_clip_starts():
    motions = [make_features(70, 0), make_features(80, 1), make_features(30, 2)]
    mean, std = np.zeros(D, np.float32), np.full(D, 2.0, np.float32)
    anywhere = (70 - 64 + 1) + (80 - 64 + 1)  # 24
    half = MotionWindowDataset(motions, mean, std, window=64, start_windows=0.5)
    assert (half.num_anywhere, len(half), half.at_start) == (anywhere, 2 * anywhere, False)
    assert torch.allclose(half[10], torch.from_numpy(motions[1][3:67] / 2))  # a window anywhere, as before

    def is_window(x, k, offset):
        return torch.allclose(x, torch.from_numpy(motions[k][offset : offset + 64] / 2))

    def where(x):
        return next((k, o) for k in (0, 1) for o in range(motions[k].shape[0] - 63) if is_window(x, k, o))

    # Before the switch the extra indices are windows anywhere, spread over both clips.
    before = [where(half[anywhere + i]) for i in range(anywhere)]
    assert len({k for k, _ in before}) == 2 and len(set(before)) > anywhere // 2
    half.at_start = True  # the refinement's switch: each long-enough clip's first 64 frames in turn
    assert half.at_start and all(is_window(half[anywhere + i], i % 2, 0) for i in range(anywhere))
    assert is_window(half[10], 1, 3)  # the other indices stay what they were
    quarter = MotionWindowDataset(motions, mean, std, window=64, start_windows=0.25)
    assert len(quarter) - anywhere == 8  # 24 * 0.25 / 0.75
    assert len(MotionWindowDataset(motions, mean, std, window=64)) == anywhere
    for bad in (1.0, -0.1):
        with pytest.raises(ValueError, match=rf"refine.start_windows={bad}: .*\[0, 1\)"):
            MotionWindowDataset(motions, mean, std, window=64, start_windows=bad)


def test_a_loader_batch_of_windows_equals_the_windows_one_by_one():
    """__getitems__ normalizes a batch at once: the same numbers to the bit, clip starts included."""
    rng = np.random.default_rng(0)
    motions = [rng.normal(size=(n, D)).astype(np.float32) for n in (70, 96, 64)]
    mean, std = rng.normal(size=D).astype(np.float32), rng.uniform(0.1, 3.0, D).astype(np.float32)
    ds = MotionWindowDataset(motions, mean, std, window=64, start_windows=0.5)
    indices = [0, 5, 40, 7, ds.num_anywhere + 3, len(ds) + 2, ds.num_anywhere]
    for at_start in (False, True):
        ds.at_start = at_start
        batch = ds.__getitems__(indices)
        assert len(batch) == len(indices)
        assert all(torch.equal(window, ds[i]) for window, i in zip(batch, indices))
        loader = torch.utils.data.DataLoader(ds, batch_size=4, shuffle=False)
        assert torch.equal(torch.cat(list(loader)), torch.stack([ds[i] for i in range(len(ds))]))


def test_the_clip_start_switch_reaches_loader_workers():
    motions = [make_features(70, 0), make_features(80, 1)]
    ds = MotionWindowDataset(motions, np.zeros(D, np.float32), np.ones(D, np.float32), start_windows=0.5)
    loader = torch.utils.data.DataLoader(ds, batch_size=len(ds), num_workers=1, persistent_workers=True)
    first = next(iter(loader))
    ds.at_start = True  # set in this process after the worker started
    second = next(iter(loader))
    n = ds.num_anywhere
    assert torch.equal(first[:n], second[:n]) and not torch.equal(first[n:], second[n:])
    assert all(torch.allclose(second[n + i], torch.from_numpy(motions[i % 2][:64])) for i in range(n))


def test_text_motion_dataset_crops_like_the_reference_and_collate_pads(tmp_path):
    write_dataset(
        tmp_path,
        {"000000": (199, [WHOLE, "another#another/DET#0.0#0.0"]), "000001": (45, [WHOLE])},
        {"train": ["000000", "000001"]},
    )
    items, _ = load_items(tmp_path, "train", feature_dim=D, fps=20, min_length=40)
    mean, std = load_stats(tmp_path, D)
    ds = TextMotionDataset(items, mean, std)
    lengths = {ds[2 * k]["length"] for k in range(200)}  # item 0, tagged with 200 epochs
    assert lengths == {196, 192}  # 199 -> 196 (a multiple of 4, at most 196) or one unit shorter
    captions = {ds[2 * k]["caption"] for k in range(50)}
    assert captions == {"a person walks forward", "another"}
    assert ds[0]["motion"].equal(ds[0]["motion"])  # a sample is a function of its index
    sample = ds[1]
    assert sample["length"] in (44, 40) and sample["motion"].shape == (sample["length"], D)
    offset_found = any(
        np.allclose(
            sample["motion"].numpy(), (items[1].features[o : o + sample["length"]] - mean) / std, atol=1e-5
        )
        for o in range(0, 6)
    )
    assert offset_found
    batch = collate_motions([ds[0], ds[1]])
    assert batch["motion"].shape[0] == 2 and batch["motion"].shape[1] == int(batch["lengths"].max())
    short = int(batch["lengths"][1])
    assert torch.all(batch["motion"][1, short:] == 0)
    eval_ds = TextMotionDataset(items, mean, std, random_crop=False)
    assert eval_ds[0]["length"] == 196 and eval_ds[0]["caption"] == "a person walks forward"


@dataclass
class _DataOnly:
    data: DataConfig = field(default_factory=DataConfig)


@pytest.mark.parametrize("option", sorted(p.stem for p in (conf_dir() / "data").glob("*.yaml")))
def test_every_data_config_loads(option):
    cfg = to_object(compose("data_check", [f"data={option}"], schema=_DataOnly)).data
    assert cfg.name == option
    assert cfg.feature_dim == (251 if option == "kit" else 263)
    assert cfg.fps == (12.5 if option == "kit" else 20.0)


def test_config_overrides_and_errors():
    cfg = compose("data_check", ["data.batch_size=7", "data.on_invalid=skip"], schema=_DataOnly)
    assert cfg.data.batch_size == 7 and cfg.data.on_invalid == "skip"
    with pytest.raises(ConfigError, match="batchsize"):
        compose("data_check", ["data.batchsize=7"], schema=_DataOnly)
    with pytest.raises(ConfigError, match="options: humanml3d, kit, synthetic"):
        compose("data_check", ["data=nope"], schema=_DataOnly)
    with pytest.raises(ConfigError, match="not key=value"):
        compose("data_check", ["data.batch_size"], schema=_DataOnly)


@pytest.mark.parametrize(
    "override, message",
    [
        ("data.min_length=0", "data.min_length=0: must be a whole number of at least 1"),
        ("data.length_limit=40", r"data.length_limit=40: must be a whole number of at least 41 \(more than"),
        ("data.max_length=2", "data.max_length=2: must be a whole number of at least 4"),
        ("data.fps=0", "data.fps=0.0: must be a number of frames per second above 0"),
        ("data.fps=nan", "data.fps=nan"),
    ],
)
def test_length_rules_and_frame_rate_out_of_range_are_refused(override, message):
    with pytest.raises(ConfigError, match=message):
        to_object(compose("data_check", [override], schema=_DataOnly))
    # The edges that are allowed: one frame, a limit one above it, a crop of one code.
    edge = to_object(
        compose(
            "data_check", ["data.min_length=1", "data.length_limit=2", "data.max_length=4"], schema=_DataOnly
        )
    ).data
    assert (edge.min_length, edge.length_limit, edge.max_length) == (1, 2, 4)


def test_datamodules_produce_batches(tmp_path):
    clips = {f"{i:06d}": (60 + 10 * i, [WHOLE]) for i in range(6)}
    write_dataset(
        tmp_path, clips, {"train": list(clips)[:4], "val": list(clips)[4:], "test": list(clips)[4:]}
    )
    cfg = DataConfig(root=str(tmp_path), batch_size=3)
    stage1 = TokenizerDataModule(cfg)
    stage1.prepare_data()
    stage1.setup("fit")
    batch = next(iter(stage1.train_dataloader()))
    assert batch.shape == (3, 64, D)
    val = next(iter(stage1.val_dataloader()))
    assert val["lengths"].tolist() == [100, 108] and val["names"] == [
        "000004",
        "000005",
    ]  # cut to multiples of 4
    # Clip 000000 (60 frames) is shorter than a window; the others give T - 63 windows each.
    assert len(stage1.datasets["train"]) == (70 - 63) + (80 - 63) + (90 - 63)
    stage2 = TextMotionDataModule(cfg)
    stage2.setup("fit")
    batch = next(iter(stage2.train_dataloader()))
    assert batch["motion"].shape[0] == 3 and batch["motion"].shape[2] == D
    assert all(length % 4 == 0 for length in batch["lengths"].tolist())
    assert "test" not in stage2.datasets


def test_stage2_draws_the_training_items_whose_caption_matches_several_times(tmp_path, caplog):
    from mmm.data.datamodule import TokenTextDataModule
    from mmm.data.resumable import ShardedRandomSampler

    twice = "a person jumps twice#a/DET person/NOUN jump/VERB twice/ADV#0.0#0.0"
    clips = {f"{i:06d}": (60 + 4 * i, [twice if i in (1, 3, 4) else WHOLE]) for i in range(6)}
    write_dataset(
        tmp_path, clips, {"train": list(clips)[:4], "val": list(clips)[4:], "test": list(clips)[4:]}
    )
    overrides = ["data.oversample.pattern=TWICE|three times", "data.oversample.factor=3"]
    cfg = to_object(compose("data_check", overrides, schema=_DataOnly)).data
    cfg.root, cfg.synthesize = str(tmp_path), None
    tokenizer = SimpleNamespace(quantizers={"codes": SimpleNamespace(num_codes=16)})
    stage2 = TokenTextDataModule(cfg, 0, tokenizer, "tok", None, None, str(tmp_path / "tokens"))
    stage2.tokens = {name: np.zeros(length // 4, dtype=np.int64) for name, (length, _) in clips.items()}
    with caplog.at_level("INFO"):
        stage2.setup("fit")
    # 2 of 4 training items match (case-insensitively), each three times: 2 + 2 * 3 draws an epoch;
    # validation is left as it is although 000004 matches.
    train = stage2.datasets["train"]
    names = ["000000", "000001", "000001", "000001", "000002", "000003", "000003", "000003"]
    assert sorted(item.name for item in train.items) == names
    assert [item.name for item in stage2.datasets["val"].items] == ["000004", "000005"]
    assert "2 of 4 training items" in caplog.text and "(8 draws per epoch)" in caplog.text
    # An epoch of the sampler draws each matched item three times, in a new order each epoch.
    sampler = ShardedRandomSampler(len(train), seed=0)
    epochs = []
    for epoch in (0, 1):
        sampler.set_epoch(epoch)
        epochs.append([train[i]["name"] for i in sampler])
    assert sorted(epochs[0]) == sorted(epochs[1]) == names and epochs[0] != epochs[1]
    # The evaluator's data (TextMotionDataModule) reads every item once.
    evaluator = TextMotionDataModule(cfg)
    evaluator.setup("fit")
    assert sorted(item.name for item in evaluator.datasets["train"].items) == [
        "000000",
        "000001",
        "000002",
        "000003",
    ]
    # Off by default; the pattern and factor are checked.
    items = evaluator.datasets["train"].items
    assert oversample_items(items, OversampleConfig()) is items
    with pytest.raises(ValueError, match=r"data.oversample.pattern='\(' is not a regular expression"):
        oversample_items(items, OversampleConfig(pattern="("))
    with pytest.raises(ValueError, match="data.oversample.factor=0 must be a whole number"):
        oversample_items(items, OversampleConfig(pattern="x", factor=0))
    with caplog.at_level(logging.WARNING, logger="mmm.data.datamodule"):
        assert oversample_items(items, OversampleConfig(pattern="thrice")) == items
    none_matched = "none of the 4 training items has a caption matching .*'thrice'"
    assert re.search(none_matched, caplog.text), caplog.text


def test_datamodule_refuses_a_missing_folder_without_synthesis(tmp_path):
    dm = TokenizerDataModule(DataConfig(root=str(tmp_path / "absent"), synthesize=None))
    with pytest.raises(DataError, match="absent: dataset folder does not exist; point data.root"):
        dm.prepare_data()


def test_load_clips_keeps_long_clips_for_the_tokenizer(tmp_path):
    write_dataset(
        tmp_path, {"000000": (250, [WHOLE]), "000001": (50, [WHOLE])}, {"train": ["000000", "000001"]}
    )
    clips, report = load_clips(tmp_path, "train", feature_dim=D, min_length=64)
    assert list(clips) == ["000000"] and clips["000000"].shape == (250, D)
    assert report.skipped["clip shorter than 64 frames"] == 1


def test_preview_recovers_joints_from_features_when_a_dataset_has_no_new_joints(
    reference_dir, tmp_path, caplog
):
    """A dataset shipped with new_joint_vecs/ only is previewed from its features: the recovered
    joints are HumanML3D's own new_joints/ (to float rounding), and the log says which clips."""
    import shutil

    from PIL import Image

    from mmm.data.preview import clip_joints, preview_dataset

    source = reference_dir / "humanml3d"
    root = tmp_path / "features-only"
    (root / "new_joint_vecs").mkdir(parents=True)
    (root / "texts").mkdir()
    shutil.copy(source / "new_joint_vecs/012314.npy", root / "new_joint_vecs/012314.npy")
    (root / "texts/012314.txt").write_text(WHOLE + "\n")
    (root / "test.txt").write_text("012314\n")
    joints, recovered = clip_joints(root, "012314")
    expected = np.load(source / "new_joints/012314.npy")
    assert recovered and joints.shape == expected.shape == (170, 22, 3)
    np.testing.assert_allclose(joints, expected, atol=1e-5)
    assert clip_joints(source, "012314")[1] is False  # new_joints/ is read when it is there
    with caplog.at_level("INFO", logger="mmm.data.preview"):
        written = preview_dataset(root, tmp_path / "preview", count=3)
    assert [p.name for p in written] == ["012314.gif", "contact_sheet.png"]
    assert Image.open(written[0]).n_frames == 170
    assert "1 of 1 clips have no new_joints/ file (012314)" in caplog.text
    (root / "new_joint_vecs/012314.npy").unlink()
    with pytest.raises(DataError, match=r"new_joints/012314\.npy: the clip has neither joints nor features"):
        preview_dataset(root, tmp_path / "again")
    assert not (tmp_path / "again").exists()

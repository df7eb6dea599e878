"""benchmarks/adherence_diagnosis.py's bookkeeping, with an oracle model: its "generation" is each
caption's own motion and its round trip is exact, so every figure the script reports must be the
labelled data's own, counted here independently with the checker."""

import importlib.util
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mmm.data.synthetic.adherence import FPS, check_in_order, check_motion, mean_speed
from mmm.data.synthetic.generate import generate_dataset
from mmm.motion.features import recover_from_ric
from mmm.tokenizer.search import CodeSearchConfig

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "adherence_diagnosis.py"


@pytest.fixture(scope="module")
def diagnosis():
    spec = importlib.util.spec_from_file_location("adherence_diagnosis", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("diagnosis") / "ds"
    generate_dataset(root, num_clips=80, seed=3, progress=False)
    return root


class Oracle:
    """Generates each caption's own motion (the rows of `items`: caption, frames, parts, features)."""

    max_frames, unit = 196, 4

    def __init__(self, items):
        self.motion = {row[0]: row[3] for row in items}
        self.tokenizer = SimpleNamespace(encode_cfg=CodeSearchConfig())
        self.encoded_with = []  # the code search's candidates at each encode

    def to_joints(self, features):
        return recover_from_ric(np.asarray(features, dtype=np.float32), 22)

    def generate(self, texts, frames, sampling=None, seed=0, check_lengths=True):
        return SimpleNamespace(joints=[self.to_joints(self.motion[t][:n]) for t, n in zip(texts, frames)])

    def encode_motions(self, motions):
        self.encoded_with.append(self.tokenizer.encode_cfg.candidates)
        return list(motions)

    def decode(self, codes):
        return codes


def test_an_oracles_figures_are_the_datas_own(diagnosis, dataset):
    rows = diagnosis.labelled_items(dataset, "test", SimpleNamespace(max_frames=196, unit=4), features=True)
    # One row per caption text (the oracle looks motions up by caption).
    seen, items = set(), []
    for row in rows:
        if row[0] not in seen:
            seen.add(row[0])
            items.append(row)
    assert len(items) >= 20
    model = Oracle(items)

    def own(row):
        joints = model.to_joints(row[3])
        frames, parts = row[1], row[2]
        return check_motion(joints, parts), check_in_order(
            joints, parts, min(40, frames // len(parts))
        ) is not None

    expected = [own(row) for row in items]

    # round_trip: every item, its own motion back.
    report = diagnosis.round_trip(model, items)
    assert report["all"] == {
        "followed": sum(o for _, o in expected),
        "of": len(items),
        "rate": sum(o for _, o in expected) / len(items),
    }
    singles = [o for row, (_, o) in zip(items, expected) if len(row[2]) == 1]
    assert report["single"]["of"] == len(singles) and report["single"]["followed"] == sum(singles)
    walks = [o for row, (_, o) in zip(items, expected) if [p["action"] for p in row[2]] == ["walk"]]
    if walks:
        assert (report["walk"]["followed"], report["walk"]["of"]) == (sum(walks), len(walks))

    # failures: the checker's failed conditions per action, counted.
    generated = diagnosis.generated_checks(model, [row[:3] for row in items], batch=7)
    assert [r[3] for r in generated] == [o for _, o in expected]
    table = diagnosis.failures(generated)
    counted = Counter()
    for row, (result, _) in zip(items, expected):
        key = row[2][0]["action"] if len(row[2]) == 1 else "composition"
        counted.update(f"{key}|{c.action}: {c.name}" for c in result.failures)
    assert {f"{k}|{name}": n for k, v in table.items() for name, n in v["failed"].items()} == dict(counted)
    assert sum(v["captions"] for v in table.values()) == len(items)

    # phrasing: seen against new captions, as the training captions say.
    training = {row[0] for row in items[::2]}
    split = diagnosis.phrasing(generated, training)
    assert sum(v["of"] for v in split.values()) == len(items)
    seen_single = [o for row, (_, o) in zip(items, expected) if len(row[2]) == 1 and row[0] in training]
    assert split["single, caption seen in training"]["of"] == len(seen_single)
    assert split["single, caption seen in training"]["followed"] == sum(seen_single)

    # locomotion_speeds: every source is the data; the generated ones twice (sampler seeds 0 and 1).
    model.encoded_with.clear()
    speeds = diagnosis.locomotion_speeds(model, items)
    gaits = [
        (
            row,
            row[2][0]["action"]
            + (f"-{row[2][0]['params']['speed']}" if row[2][0]["action"] == "walk" else ""),
        )
        for row in items
        if len(row[2]) == 1 and row[2][0]["action"] in ("run", "walk")
    ]
    assert set(speeds) == {g for _, g in gaits} and speeds
    for gait, sources in speeds.items():
        mine = [row for row, g in gaits if g == gait]
        data_speed = float(np.mean([mean_speed(model.to_joints(row[3]), FPS) for row in mine]))
        passed = sum(check_motion(model.to_joints(row[3]), row[2]).passed for row in mine)
        assert sources["data"] == pytest.approx(
            {"speed": data_speed, "passed": passed, "of": len(mine), "draws_per_item": 1}
        )
        assert sources["nearest-code round trip"] == sources["data"]
        for name in diagnosis.SPEED_SAMPLING:
            assert sources[name] == pytest.approx(
                {"speed": data_speed, "passed": 2 * passed, "of": 2 * len(mine), "draws_per_item": 2}
            )
    # The nearest codes (one candidate) for the round trip stage 2 learns from, then the search restored.
    assert model.encoded_with == [1] and model.tokenizer.encode_cfg == CodeSearchConfig()

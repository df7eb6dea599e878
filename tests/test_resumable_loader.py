"""The resumable, self-sharding sampler and loader."""

import torch

from mmm.data import resumable as sampling
from mmm.data.resumable import ResumableDataLoader, ShardedRandomSampler


def test_shards_cover_the_epoch_and_differ_by_epoch(monkeypatch):
    shards = []
    for rank in (0, 1):
        monkeypatch.setattr(sampling, "_rank_and_world", lambda rank=rank: (rank, 2))
        s = ShardedRandomSampler(11, seed=3)
        s.set_epoch(5)
        shards.append(list(s))
        assert len(s) == 6
    assert len(shards[0]) == len(shards[1]) == 6
    # Tagged with epoch 5: index + 5 * 11; one index repeated to pad.
    assert {i - 55 for i in shards[0] + shards[1]} == set(range(11))
    monkeypatch.setattr(sampling, "_rank_and_world", lambda: (0, 1))
    a, b = ShardedRandomSampler(50, seed=3), ShardedRandomSampler(50, seed=3)
    b.set_epoch(1)
    assert sorted(a) == list(range(50)) and [i % 50 for i in b] != list(a)
    assert list(ShardedRandomSampler(5, shuffle=False)) == [0, 1, 2, 3, 4]


class Numbers(torch.utils.data.Dataset):
    def __len__(self):
        return 40

    def __getitem__(self, index):  # indices arrive tagged with the epoch
        return float(index % 40)


def test_loader_resumes_mid_epoch_exactly():
    data = Numbers()
    full = ResumableDataLoader(data, batch_size=4, shuffle=True, seed=7)
    full.sampler.set_epoch(2)
    expected = [b.tolist() for b in full]
    interrupted = ResumableDataLoader(data, batch_size=4, shuffle=True, seed=7)
    interrupted.sampler.set_epoch(2)
    it = iter(interrupted)
    seen = [next(it).tolist() for _ in range(3)]
    state = interrupted.state_dict()
    assert state == {"epoch": 2, "batches": 3}
    resumed = ResumableDataLoader(data, batch_size=4, shuffle=True, seed=7)
    resumed.load_state_dict(state)
    rest = [b.tolist() for b in resumed]
    assert seen + rest == expected
    assert resumed.state_dict() == {"epoch": 2, "batches": 10}


def test_a_position_at_the_end_of_an_epoch_resumes_with_the_whole_next_epoch():
    """A checkpoint written after an epoch's last batch holds (epoch, all its batches); the trainer
    then starts the next epoch (set_epoch), which must begin at its first batch, not skip as many."""
    data = Numbers()
    full = ResumableDataLoader(data, batch_size=4, shuffle=True, seed=7)
    full.sampler.set_epoch(3)
    expected = [b.tolist() for b in full]
    resumed = ResumableDataLoader(data, batch_size=4, shuffle=True, seed=7)
    resumed.load_state_dict({"epoch": 2, "batches": 10})
    resumed.sampler.set_epoch(3)
    assert [b.tolist() for b in resumed] == expected and len(expected) == 10
    # Lightning may also finish the restored epoch first: its rest is empty, the next is whole.
    again = ResumableDataLoader(data, batch_size=4, shuffle=True, seed=7)
    again.load_state_dict({"epoch": 2, "batches": 10})
    again.sampler.set_epoch(2)
    assert [b.tolist() for b in again] == []
    again.sampler.set_epoch(3)
    assert [b.tolist() for b in again] == expected

"""A sampler and loader that resume mid-epoch exactly, and shard across DDP ranks by themselves.

Lightning restores a training dataloader's position when the loader has state_dict() and
load_state_dict(); plain DataLoaders restart the epoch, so a resumed run would see other batches
than an uninterrupted one. Here the epoch's order is a permutation seeded by (seed, epoch), each
rank takes every world_size-th index of it (padded to equal length, as DistributedSampler does),
and the loader's state is (epoch, batches yielded). Use with Trainer(use_distributed_sampler=False).
"""

from __future__ import annotations

from typing import Iterator

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Sampler


def _rank_and_world() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


class ShardedRandomSampler(Sampler[int]):
    """This rank's share of a (seed, epoch)-seeded permutation of range(n) (or range(n) in order).

    Indices are tagged with the epoch (index + epoch * n): a dataset takes `index % len(self)`
    and may seed its per-sample randomness with the tagged value, so every epoch draws anew.
    """

    def __init__(self, n: int, seed: int = 0, shuffle: bool = True):
        self.n, self.seed, self.shuffle = n, seed, shuffle
        self.epoch = 0
        self.skip = 0  # indices of this epoch already consumed (set when resuming)

    def set_epoch(self, epoch: int) -> None:
        # A resumed position belongs to its epoch. A checkpoint written after an epoch's last batch
        # holds (that epoch, all its batches), and the trainer goes on with the next epoch, which
        # starts at its first index (keeping the skip would drop that whole epoch too).
        if epoch != self.epoch:
            self.skip = 0
        self.epoch = epoch

    def _indices(self) -> list[int]:
        rank, world = _rank_and_world()
        if self.shuffle:
            g = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
            order = torch.randperm(self.n, generator=g).tolist()
        else:
            order = list(range(self.n))
        per_rank = -(-self.n // world)
        order += order[: per_rank * world - self.n]
        return [i + self.epoch * self.n for i in order[rank::world]]

    def __iter__(self) -> Iterator[int]:
        indices = self._indices()[self.skip :]
        self.skip = 0
        return iter(indices)

    def __len__(self) -> int:
        _, world = _rank_and_world()
        return -(-self.n // world)


class ResumableDataLoader(DataLoader):
    """A DataLoader over a ShardedRandomSampler whose position survives a checkpoint."""

    def __init__(
        self, dataset, batch_size: int, *, shuffle: bool, seed: int = 0, drop_last: bool = False, **kwargs
    ):
        sampler = ShardedRandomSampler(len(dataset), seed=seed, shuffle=shuffle)
        # Its own generator: starting an iterator draws a seed for the workers, and drawing it
        # from the global generator would shift every later random number after a resume.
        generator = torch.Generator().manual_seed(seed)
        super().__init__(
            dataset,
            batch_size=batch_size,
            sampler=sampler,
            drop_last=drop_last,
            generator=generator,
            **kwargs,
        )
        self._yielded = 0
        self._epoch_of_state = 0

    def __iter__(self):
        self._epoch_of_state = self.sampler.epoch
        self._yielded = self.sampler.skip // self.batch_size
        for batch in super().__iter__():
            self._yielded += 1
            yield batch

    def state_dict(self) -> dict:
        return {"epoch": self._epoch_of_state, "batches": self._yielded}

    def load_state_dict(self, state: dict) -> None:
        self.sampler.set_epoch(int(state["epoch"]))
        self.sampler.skip = int(state["batches"]) * self.batch_size

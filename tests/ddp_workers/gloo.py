"""Two CPU processes over gloo for the workers that call collectives themselves (no Trainer):
`spawn_two_ranks(work, out_dir)` runs work(rank, out_dir) in each, inside a process group on a
free port of 127.0.0.1, and ends the group when both are done. A script started as one of two ranks
(LOCAL_RANK and MASTER_PORT set, as tests/helpers/forked.py starts them) runs its own rank instead.
"""

import os
import socket

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

WORLD = 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(rank: int, work, port: int, out_dir: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=WORLD)
    try:
        work(rank, out_dir)
        dist.barrier()
    finally:
        dist.destroy_process_group()


def spawn_two_ranks(work, out_dir: str) -> None:
    if "LOCAL_RANK" in os.environ:  # started as one of the ranks (tests/helpers/forked.py): join the others
        _run(int(os.environ["LOCAL_RANK"]), work, int(os.environ["MASTER_PORT"]), out_dir)
    else:
        mp.spawn(_run, args=(work, _free_port(), out_dir), nprocs=WORLD, join=True)

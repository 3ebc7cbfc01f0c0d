"""Batches for training: a seeded, rank-sharded batch sampler that can start mid-epoch.

Every epoch is one permutation of the items seeded by (seed, epoch), identical on every rank;
rank r takes every world_size-th item of it (``usl.records.partition``), so ranks never share an
item. The tail that does not fill a batch on every rank is left out of that epoch (a later
epoch's permutation covers it), which keeps the number of steps equal on all ranks, as DDP needs.
"""

from __future__ import annotations

import multiprocessing
from typing import Iterator

import torch
from torch.utils.data import DataLoader, Sampler

from usl.records import partition

from .dataset import MultiViewDataset, SampleKey
from .samples import collate_samples


class ShardedBatchSampler(Sampler[list[SampleKey]]):
    def __init__(
        self, num_items: int, batch_size: int, rank: int = 0, world_size: int = 1, seed: int = 0, shuffle: bool = True
    ):
        if num_items // world_size < batch_size:
            raise ValueError(
                f"{num_items} items cannot fill one batch of {batch_size} on each of {world_size} process(es)"
            )
        self.num_items, self.batch_size = num_items, batch_size
        self.rank, self.world_size = rank, world_size
        self.seed, self.shuffle = seed, shuffle
        self.epoch, self.start_batch = 0, 0

    def set_epoch(self, epoch: int, start_batch: int = 0) -> None:
        """Iterate epoch ``epoch`` from its ``start_batch``-th batch on (for exact resume)."""
        self.epoch, self.start_batch = epoch, start_batch

    def __len__(self) -> int:
        """Batches per epoch on each rank (a full epoch, whatever ``start_batch`` is)."""
        return self.num_items // self.world_size // self.batch_size

    def epoch_items(self) -> list[int]:
        if self.shuffle:
            generator = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
            return torch.randperm(self.num_items, generator=generator).tolist()
        return list(range(self.num_items))

    def __iter__(self) -> Iterator[list[SampleKey]]:
        mine = partition(self.epoch_items(), self.rank, self.world_size)
        for batch in range(self.start_batch, len(self)):
            chunk = mine[batch * self.batch_size : (batch + 1) * self.batch_size]
            yield [SampleKey(index, self.epoch) for index in chunk]


def _worker_init(_: int) -> None:
    torch.set_num_threads(1)  # workers decode PNGs and RLE; keep cores for the main process


def worker_start_method() -> str:
    """How loader workers start: never by ``fork``. The training process is multi-threaded (torch's
    and OpenMP's pools, gloo), and a forked child inherits their locks in whatever state they were:
    with CUDA builds of torch on Python 3.13 such a child crashed on its first lazy import
    (``torch._dynamo`` and triton, pulled in by the fused Adam optimizer). ``forkserver`` forks from
    a clean single-threaded server; where it does not exist (Windows), ``spawn``."""
    return "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


def build_train_loader(
    dataset: MultiViewDataset, sampler: ShardedBatchSampler, num_workers: int, pin_memory: bool = False
) -> DataLoader:
    """``pin_memory`` (for a CUDA run): batches arrive page-locked, so their copy to the device overlaps.
    Workers start once (``persistent_workers``): each starts a fresh interpreter that imports torch."""
    return DataLoader(
        dataset,
        batch_sampler=sampler,
        num_workers=num_workers,
        collate_fn=collate_samples,
        pin_memory=pin_memory,
        worker_init_fn=_worker_init if num_workers else None,
        multiprocessing_context=worker_start_method() if num_workers else None,
        persistent_workers=num_workers > 0,
        # Its own generator: creating an iterator must not draw from the global RNG, or a resumed
        # run (new iterator mid-epoch) would continue with different random numbers.
        generator=torch.Generator().manual_seed(0),
    )

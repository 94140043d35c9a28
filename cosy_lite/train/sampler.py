"""Data order as a pure function of (seed, step): what makes resuming exact.

Batch ``s`` of the run is the ``s``-th slice of the concatenated epoch permutations, each epoch
shuffled with its own seed; under DDP each process takes its ``rank``-th share of the global batch.
A run resumed at step ``s`` therefore sees exactly the batches the uninterrupted run would have.
"""

from __future__ import annotations

from typing import Iterator

import torch
from torch.utils.data import Sampler


class StepBatchSampler(Sampler[list[int]]):
    """Yields per-process index lists for steps ``start_step .. total_steps - 1``.

    Args:
        n_items: dataset length; batch_size: per-process batch size; seed: data-order seed;
        rank / world_size: this process's share of the global batch (``batch_size * world_size``).
    """

    def __init__(self, n_items: int, batch_size: int, seed: int, start_step: int, total_steps: int,
                 rank: int = 0, world_size: int = 1):
        if n_items <= 0:
            raise ValueError("the training set is empty")
        self.n_items, self.batch_size, self.seed = n_items, batch_size, seed
        self.start_step, self.total_steps = start_step, total_steps
        self.rank, self.world_size = rank, world_size
        self._perms: dict[int, torch.Tensor] = {}

    def _perm(self, epoch: int) -> torch.Tensor:
        if epoch not in self._perms:
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
            self._perms = {epoch: torch.randperm(self.n_items, generator=g)}
        return self._perms[epoch]

    def indices_for_step(self, step: int) -> list[int]:
        global_batch = self.batch_size * self.world_size
        start = step * global_batch + self.rank * self.batch_size
        out = []
        for pos in range(start, start + self.batch_size):
            epoch, i = divmod(pos, self.n_items)
            out.append(int(self._perm(epoch)[i]))
        return out

    def __iter__(self) -> Iterator[list[int]]:
        for step in range(self.start_step, self.total_steps):
            yield self.indices_for_step(step)

    def __len__(self) -> int:
        return max(0, self.total_steps - self.start_step)

"""ContiguousBatchSampler: every sample once, and each DataLoader worker (and process) reads a
contiguous run of samples, so per-worker caches of neighbouring frames hit."""

import pytest
from torch.utils.data import DataLoader, Dataset, get_worker_info

from pcdet_atlas.datasets.loader import ContiguousBatchSampler


class _WhoReads(Dataset):
    def __init__(self, n):
        self.n = n

    def __len__(self):
        return self.n

    def __getitem__(self, index):
        info = get_worker_info()
        return index, -1 if info is None else info.id


CASES = [(40, 1, 2, 1), (41, 2, 3, 1), (7, 3, 4, 1), (50, 1, 2, 3), (0, 1, 2, 1), (5, 8, 2, 2)]


@pytest.mark.parametrize("n,batch,workers,world", CASES)
def test_every_sample_once_and_contiguous_per_worker(n, batch, workers, world):
    seen = []
    for rank in range(world):
        sampler = ContiguousBatchSampler(n, batch, workers, rank, world)
        assert len(sampler) == len(list(sampler))
        # the DataLoader hands batch i to worker i % workers
        per_worker: dict[int, list[int]] = {}
        for i, b in enumerate(sampler):
            assert b == list(range(b[0], b[0] + len(b)))  # a batch is a contiguous range
            per_worker.setdefault(i % max(workers, 1), []).extend(b)
            seen.extend(b)
        shard = [i for w in sorted(per_worker) for i in per_worker[w]]
        if shard:  # each process: one contiguous shard, in order worker by worker
            assert shard == list(range(shard[0], shard[0] + len(shard)))
    assert sorted(seen) == list(range(n))


def test_workers_read_contiguous_runs_through_a_dataloader():
    n, workers = 24, 2
    loader = DataLoader(
        _WhoReads(n), batch_sampler=ContiguousBatchSampler(n, 1, workers), num_workers=workers
    )
    by_worker: dict[int, list[int]] = {}
    for index, worker in loader:
        by_worker.setdefault(int(worker), []).append(int(index))
    assert by_worker == {0: list(range(12)), 1: list(range(12, 24))}
    # a plain in-order loader interleaves the workers: no worker sees neighbouring frames
    plain: dict[int, list[int]] = {}
    for index, worker in DataLoader(_WhoReads(n), batch_size=1, num_workers=workers):
        plain.setdefault(int(worker), []).append(int(index))
    assert plain[0] == list(range(0, n, 2))


def test_bad_arguments():
    for kwargs in ({"batch_size": 0}, {"num_workers": -1}, {"rank": 2, "world_size": 2}):
        args = {"num_samples": 10, "batch_size": 1, **kwargs}
        with pytest.raises(ValueError, match="ContiguousBatchSampler"):
            ContiguousBatchSampler(**args)

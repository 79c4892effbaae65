"""The run's caches (EvalCaches): what each variant's loader is given and gives back."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from pcdet_atlas.train_utils.eval_caches import EvalCaches


def dataset(family: str, frames: int = 6):
    infos = [{"point_cloud": {"lidar_sequence": "seq", "sample_idx": i}} for i in range(frames)]
    return SimpleNamespace(attack=SimpleNamespace(family=family), infos=infos)


class Bank:
    """A stand-in for ProposalBank: what it was seeded with, what it holds."""

    def __init__(self, held=None):
        self.seeded, self.held = None, held or {}

    def seed(self, rows):
        self.seeded = dict(rows)

    def seedable(self):
        return dict(self.held)


def test_the_clean_variant_gives_its_proposals_and_predictions_to_the_others():
    caches = EvalCaches()
    batches = [[0, 1], [2, 3], [4, 5]]
    clean = caches.for_variant(dataset("clean"), batches, lambda seq, idx: False)
    assert clean.reused is None and clean.proposal_seed is None and clean.batches == batches
    rows = {("seq", i): np.full((1, 11), i, dtype=np.float32) for i in range(6)}
    clean.keep(Bank(rows))
    predictions = [{"frame_id": f"seq_{i}"} for i in range(6)]
    caches.keep_clean(predictions)
    assert caches.reuses_clean() and caches.clean_proposals.keys() == rows.keys()

    # frame 3 attacked: its batch (2, 3) is proposed again, the others start from the clean bank
    attack = caches.for_variant(dataset("injection"), batches, lambda seq, idx: idx == 3)
    assert attack.reused is predictions and attack.proposals_out is None
    assert sorted(attack.proposal_seed) == [("seq", i) for i in (0, 1, 4, 5)]
    bank = Bank()
    attack.seed(bank)
    assert bank.seeded.keys() == attack.proposal_seed.keys()

    caches.new_checkpoint()  # another checkpoint: nothing of the last one's clean run is used
    assert not caches.reuses_clean() and caches.clean_proposals == {}
    again = caches.for_variant(dataset("injection"), batches, lambda seq, idx: False)
    assert again.reused is None and again.proposal_seed is None


def test_without_reuse_every_frame_runs_but_the_clean_run_is_still_kept():
    caches = EvalCaches(reuse=False)
    caches.keep_clean([{"frame_id": "seq_0"}], {("seq", 0): np.zeros((0, 11), np.float32)})
    assert caches.clean_predictions is not None and not caches.reuses_clean()
    attack = caches.for_variant(dataset("removal"), [[0], [1]], lambda seq, idx: False)
    assert attack.reused is None and attack.proposal_seed is None
    assert caches.store_counts() is None and caches.store_counts_since(None) is None

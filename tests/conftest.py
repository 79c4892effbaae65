"""Shared pytest fixtures.

``synthetic_root``: a tiny synthetic Waymo-format dataset generated once per test session
(train: 2 sequences x 10 frames; val: 1 sequence x 70 frames, enough for one full 32-frame
attack run 32..63 plus 6 frames after it), in OpenPCDet's processed layout.
"""

from __future__ import annotations

import pytest

SYNTHETIC_FIXTURE_SEED = 0
SYNTHETIC_FIXTURE_SEQUENCES = {"train": 2, "val": 1}
SYNTHETIC_FIXTURE_FRAMES = {"train": 10, "val": 70}


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory):
    """Path of a session-cached tiny synthetic dataset (read it, do not modify it)."""
    from pcdet_atlas.datasets.synthetic import create_synthetic_waymo

    root = tmp_path_factory.mktemp("synthetic_waymo")
    create_synthetic_waymo(
        root,
        num_sequences=SYNTHETIC_FIXTURE_SEQUENCES,
        frames_per_sequence=SYNTHETIC_FIXTURE_FRAMES,
        seed=SYNTHETIC_FIXTURE_SEED,
        workers=2,
    )
    return root

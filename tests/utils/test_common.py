"""Helpers of pcdet_atlas.utils.common."""

import pytest
import torch

from pcdet_atlas.utils.common import deterministic_algorithms


@pytest.mark.parametrize("outer_warn_only", [False, True])
def test_deterministic_algorithms_sets_and_restores_the_mode(outer_warn_only):
    before = (
        torch.are_deterministic_algorithms_enabled(),
        torch.is_deterministic_algorithms_warn_only_enabled(),
    )
    try:
        torch.use_deterministic_algorithms(True, warn_only=outer_warn_only)
        with deterministic_algorithms(False):
            assert not torch.are_deterministic_algorithms_enabled()
            with deterministic_algorithms(True, warn_only=not outer_warn_only):
                assert torch.are_deterministic_algorithms_enabled()
                assert torch.is_deterministic_algorithms_warn_only_enabled() != outer_warn_only
            assert not torch.are_deterministic_algorithms_enabled()
        with pytest.raises(RuntimeError, match="inside"):
            with deterministic_algorithms(False):
                raise RuntimeError("inside")
        assert torch.are_deterministic_algorithms_enabled()
        assert torch.is_deterministic_algorithms_warn_only_enabled() == outer_warn_only
    finally:
        torch.use_deterministic_algorithms(before[0], warn_only=before[1])

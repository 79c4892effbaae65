"""The device parametrisation every CPU/GPU test uses: CUDA cases carry the ``cuda`` mark and
skip (visibly) where no CUDA device exists, instead of passing while checking nothing."""

import pytest
import torch

DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=[
            pytest.mark.cuda,
            pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
        ],
    ),
]

"""Deterministic random generators keyed by what they are for.

Every random draw in pcdet_atlas comes from a generator built here from explicit keys, e.g.
``torch_generator(seed, 'inj_global', sequence_name, run_start, 'placement')``. The seed is a hash
of the keys, so it does not depend on worker count, batch order, process, or on which other draws
were made before (no shared global RNG state across forked workers).
"""

from __future__ import annotations

import hashlib

import numpy as np
import torch

__all__ = ["derive_seed", "torch_generator", "numpy_generator"]


def _canonical(key: object) -> str:
    if isinstance(key, (bool, np.bool_)):
        return f"b:{bool(key)}"
    if isinstance(key, (int, np.integer)):
        return f"i:{int(key)}"
    if isinstance(key, (float, np.floating)):
        return f"f:{float(key)!r}"
    if isinstance(key, str):
        return f"s:{key}"
    if isinstance(key, (tuple, list)):
        return "t:(" + ",".join(_canonical(k) for k in key) + ")"
    raise TypeError(f"seed keys must be int, float, bool, str or tuples of them; got {key!r}")


def derive_seed(*keys: object) -> int:
    """A 63-bit seed from a BLAKE2b hash of the keys (stable across runs, machines, Python)."""
    text = "|".join(_canonical(k) for k in keys).encode()
    return int.from_bytes(hashlib.blake2b(text, digest_size=8).digest(), "little") >> 1


def torch_generator(*keys: object, device: str | torch.device = "cpu") -> torch.Generator:
    """A ``torch.Generator`` on ``device`` seeded with ``derive_seed(*keys)``."""
    gen = torch.Generator(device=device)
    gen.manual_seed(derive_seed(*keys))
    return gen


def numpy_generator(*keys: object) -> np.random.Generator:
    """A numpy ``Generator`` (PCG64) seeded with ``derive_seed(*keys)``."""
    return np.random.default_rng(derive_seed(*keys))

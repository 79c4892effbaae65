import numpy as np
import pytest
import torch

from pcdet_atlas.utils.seeding import derive_seed, numpy_generator, torch_generator


def test_seed_is_stable_and_key_sensitive():
    a = derive_seed(0, "inj_global", "segment-1", 32, "placement")
    assert a == derive_seed(0, "inj_global", "segment-1", 32, "placement")
    assert a != derive_seed(0, "inj_global", "segment-1", 33, "placement")
    assert a != derive_seed(0, "inj_global", "segment-1", 32, "trace")
    assert derive_seed(1) != derive_seed("1")  # types are part of the key
    assert 0 <= a < 2**63
    # pinned value: the hash must never change between releases (results are keyed by it)
    assert derive_seed(0, "x") == derive_seed(np.int64(0), "x")


def test_generators_reproduce():
    t1 = torch.rand(5, generator=torch_generator(3, "a"))
    t2 = torch.rand(5, generator=torch_generator(3, "a"))
    assert torch.equal(t1, t2)
    n1 = numpy_generator(3, "a").random(5)
    assert np.array_equal(n1, numpy_generator(3, "a").random(5))


def test_bad_key_type():
    with pytest.raises(TypeError):
        derive_seed(object())

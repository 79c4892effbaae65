"""The restricted unpickler: numpy arrays, dtypes and scalars and Python containers load (under
numpy 1.x's and 2.x's names, every pickle protocol); anything else is refused by name, before
it runs."""

from __future__ import annotations

import collections
import pathlib
import pickle

import numpy as np
import pytest
from malicious_files import Touch

from pcdet_atlas.utils.safe_pickle import RefusedGlobalError, load_pickle, loads

VALUES = {
    "float32": np.arange(6, dtype=np.float32).reshape(2, 3),
    "int64": np.arange(3, dtype=np.int64),
    "bool": np.array([True, False]),
    "unicode": np.array(["Vehicle", "Pedestrian"], dtype="<U10"),
    "object_strings": np.array(["Vehicle", "Cyclist", None], dtype=object),
    "structured": np.zeros(2, dtype=[("a", "<f4"), ("b", "<i8")]),
    "empty": np.zeros((0, 7), dtype=np.float32),
    "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
    "scalars": [np.float32(1.5), np.float64(2.0), np.int64(3), np.bool_(True), np.str_("x")],
    "dtype": np.dtype("<f4"),
    "containers": (
        {1, 2}, frozenset({3}), 1 + 2j, slice(1, 5, 2), b"", b"xy", bytearray(b"z"),
        collections.OrderedDict(a=1), {"k": [None, True, 1.5, "s"]},
    ),
}  # fmt: skip


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tolist() == b.tolist()
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_numpy_and_python_values_round_trip(protocol):
    data = pickle.dumps(VALUES, protocol=protocol)
    back = loads(data, source="values.pkl")
    assert list(back) == list(VALUES)
    assert all(_same(VALUES[k], back[k]) for k in VALUES)


def test_numpy_1_names_load():
    """Files written under numpy 1.x name ``numpy.core.multiarray``."""
    data = pickle.dumps([VALUES["float32"], np.float64(2.0)], protocol=2)
    old = data.replace(b"numpy._core", b"numpy.core")
    assert old != data
    array, scalar = loads(old, source="old.pkl")
    assert _same(array, VALUES["float32"]) and _same(scalar, np.float64(2.0))


@pytest.mark.parametrize("protocol", [2, 4])
def test_a_code_running_pickle_is_refused_naming_file_and_global(tmp_path, protocol):
    marker = tmp_path / "marker"
    pickle.loads(pickle.dumps(Touch(marker)))  # what pickle.load would do with the file
    assert marker.exists()
    marker.unlink()
    path = tmp_path / "infos.pkl"
    path.write_bytes(pickle.dumps({"annos": [Touch(marker)]}, protocol=protocol))
    with pytest.raises(RefusedGlobalError, match=r"infos\.pkl: refused .* global ") as err:
        load_pickle(path)
    assert not marker.exists()
    assert err.value.name in ("pathlib.Path.touch", "builtins.getattr")
    assert err.value.name in str(err.value) and err.value.path == str(path)
    assert isinstance(err.value, ValueError) and isinstance(err.value, pickle.UnpicklingError)


@pytest.mark.parametrize(
    "value, name",
    [(pathlib.PurePosixPath("a"), "pathlib.PurePosixPath"), (range(3), "builtins.range"),
     (collections.Counter(a=1), "collections.Counter")],
)  # fmt: skip
def test_other_classes_are_refused(value, name):
    with pytest.raises(RefusedGlobalError, match=rf"x\.pkl: refused to unpickle the global {name}"):
        loads(pickle.dumps(value), source="x.pkl")


def test_codecs_encode_is_for_latin1_only():
    """Protocol 2 writes bytes as ``_codecs.encode(text, 'latin1')``; no other codec."""
    payload = b"\x80\x02c_codecs\nencode\nX\x02\x00\x00\x00abX\x06\x00\x00\x00rot_13\x86R."
    with pytest.raises(pickle.UnpicklingError, match="only 'latin1'"):
        loads(payload, source="x.pkl")

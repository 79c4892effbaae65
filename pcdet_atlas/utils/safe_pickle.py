"""Reading pickles without running code.

A pickle names the callables that rebuild its objects, and ``pickle.load`` imports and calls
whichever it names (``os.system`` included): opening an info file someone sent is running their
program. Every pickle the project reads (OpenPCDet's frame infos, GT database infos,
``result.pkl``, attack metadata, caches) goes through :func:`load_pickle` / :func:`loads`
instead, whose unpickler resolves only what numpy arrays, dtypes and scalars and Python's
containers need (:data:`ALLOWED_GLOBALS`); any other name is a :class:`RefusedGlobalError`
naming the file and the refused ``module.name``, raised before anything is called.
"""

from __future__ import annotations

import _codecs
import _compat_pickle
import collections
import io
import pickle
from pathlib import Path

import numpy as np

__all__ = ["ALLOWED_GLOBALS", "RefusedGlobalError", "SafeUnpickler", "load_pickle", "loads"]


class RefusedGlobalError(pickle.UnpicklingError, ValueError):
    """A file that needs a global outside the allow-list to load (loading it could run code).

    Attributes:
        path: the file (or what the bytes came from).
        name: the refused ``module.name``.
    """

    def __init__(self, message: str, *, path: str, name: str):
        super().__init__(message)
        self.path = path
        self.name = name


def _encode_latin1(text: str, encoding: str = "utf-8", errors: str = "strict") -> bytes:
    """``_codecs.encode`` as pickle protocol 2 calls it for ``bytes`` (``'latin1'``) only."""
    if encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError(
            f"_codecs.encode with encoding {encoding!r}: only 'latin1' (how pickle protocol 2 "
            "writes bytes) is allowed"
        )
    return _codecs.encode(text, encoding, errors)


def _numpy_globals() -> dict[str, object]:
    """numpy's rebuild functions under the names numpy 1.x (``numpy.core``) and 2.x
    (``numpy._core``) write, taken from numpy's own reductions (not its private modules)."""
    reconstruct = np.zeros(1).__reduce__()[0]  # multiarray._reconstruct
    scalar = np.float32(0).__reduce__()[0]  # multiarray.scalar
    frombuffer = np.zeros(1).__reduce_ex__(5)[0]  # numeric._frombuffer (protocol 5)
    out: dict[str, object] = {"numpy.ndarray": np.ndarray, "numpy.dtype": np.dtype}
    for core in ("numpy.core", "numpy._core"):
        out[f"{core}.multiarray._reconstruct"] = reconstruct
        out[f"{core}.multiarray.scalar"] = scalar
        out[f"{core}.numeric._frombuffer"] = frombuffer
    return out


_BUILTINS = {
    "set": set,
    "frozenset": frozenset,
    "complex": complex,
    "slice": slice,
    "bytes": bytes,
    "bytearray": bytearray,
}

#: ``module.name`` -> the object it resolves to; nothing else can be named by a pickle read here
ALLOWED_GLOBALS: dict[str, object] = {
    **_numpy_globals(),
    **{f"builtins.{k}": v for k, v in _BUILTINS.items()},
    "_codecs.encode": _encode_latin1,  # how protocol 2 writes bytes
    "collections.OrderedDict": collections.OrderedDict,
}


class SafeUnpickler(pickle.Unpickler):
    """``pickle.Unpickler`` resolving only :data:`ALLOWED_GLOBALS`; ``source`` names the file
    in errors."""

    def __init__(self, file, *, source: str, **kwargs):
        super().__init__(file, **kwargs)
        self.source = source

    def find_class(self, module: str, name: str):
        # protocols < 3 write Python 2's names (``__builtin__.set``): read them as Python 3's
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        elif module in _compat_pickle.IMPORT_MAPPING:
            module = _compat_pickle.IMPORT_MAPPING[module]
        key = f"{module}.{name}"
        if key not in ALLOWED_GLOBALS:
            raise RefusedGlobalError(
                f"{self.source}: refused to unpickle the global {key}: only numpy arrays, "
                "dtypes and scalars and Python containers are read (loading it could run "
                "code); rewrite the file with plain values",
                path=self.source,
                name=key,
            )
        return ALLOWED_GLOBALS[key]


def load_pickle(path: str | Path) -> object:
    """Unpickle the file ``path`` with :class:`SafeUnpickler`.

    Raises:
        RefusedGlobalError: the file names a global outside :data:`ALLOWED_GLOBALS`.
        FileNotFoundError, OSError, EOFError, pickle.UnpicklingError: as ``pickle.load``.
    """
    with open(path, "rb") as f:
        return SafeUnpickler(f, source=str(path)).load()


def loads(data: bytes, *, source: str) -> object:
    """Unpickle ``data`` (read from ``source``, named in errors) with :class:`SafeUnpickler`."""
    return SafeUnpickler(io.BytesIO(data), source=source).load()

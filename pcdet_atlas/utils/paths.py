"""Names from data, configs and flags that become one path component, kept inside their root.

A ``frame_id``, a sequence name, an attack ``VARIANT``, ``--extra_tag`` or ``--eval_tag`` names
one file or folder under a root the user chose. :func:`safe_component` admits only such a name
(``../../x``, ``..`` or ``a/b`` would leave the root); :func:`join_under` joins several and
checks the result, symlinks resolved, still lies under the root. A path relative to a root that
data or a config gives (a GT-database object's ``path``, ``DB_INFO_PATH``, ``TRACE_LIBRARY.PATH``)
is such names joined by ``/``: :func:`relative_parts` checks it, :func:`resolve_under` joins it.
:func:`regular_file` keeps a read away from devices and FIFOs (``/dev/zero`` never ends).
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

__all__ = [
    "RELATIVE_PATH_RULE",
    "SAFE_COMPONENT_RULE",
    "UnsafePathError",
    "join_under",
    "regular_file",
    "relative_parts",
    "resolve_under",
    "safe_component",
]

_SAFE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
SAFE_COMPONENT_RULE = (
    "one file or folder name of letters, digits, '.', '_' and '-' that starts with a letter or "
    "digit (no '/', not '.' or '..')"
)
RELATIVE_PATH_RULE = (
    "a relative path: names joined by '/', each of letters, digits, '.', '_' and '-' starting "
    "with a letter or digit (not absolute, no '.', '..' or empty part)"
)


class UnsafePathError(ValueError):
    """A name that would not stay one path component under its root."""


def safe_component(value: object, what: str, source: str) -> str:
    """``value`` if it is one safe path component (:data:`SAFE_COMPONENT_RULE`), else an
    :class:`UnsafePathError` naming the value, ``what`` it is and ``source`` (where it came
    from: a file and key, a flag)."""
    if not isinstance(value, str) or _SAFE.fullmatch(value) is None:
        raise UnsafePathError(f"{what} {value!r} (from {source}) is not {SAFE_COMPONENT_RULE}")
    return value


def join_under(root: str | Path, *parts: tuple[object, str], source: str) -> Path:
    """``root / part / ...`` for ``parts`` ``(value, what)``, each a :func:`safe_component`; the
    joined path, symlinks resolved, must lie under ``root`` resolved (a second line of defence: a
    symlink inside ``root`` that leads out of it is refused too)."""
    root = Path(root)
    path = root.joinpath(*(safe_component(value, what, source) for value, what in parts))
    real_root, real = root.resolve(), path.resolve()
    if real != real_root and real_root not in real.parents:
        shown = root if real_root == root else f"{root} ({real_root})"
        raise UnsafePathError(
            f"{path} (from {source}) resolves to {real}, outside its root {shown}"
        )
    return path


def relative_parts(value: object, what: str, source: str) -> tuple[str, ...]:
    """The parts of ``value``, a path relative to its root (:data:`RELATIVE_PATH_RULE`: each
    part a :func:`safe_component`), else an :class:`UnsafePathError` naming the value, ``what`` it
    is and ``source``. Only the text is checked (no file system access): cheap enough for every
    entry of a large database; :func:`resolve_under` also follows symlinks."""
    text = os.fspath(value) if isinstance(value, os.PathLike) else value
    parts = text.split("/") if isinstance(text, str) else ()
    if not parts or any(_SAFE.fullmatch(part) is None for part in parts):
        raise UnsafePathError(f"{what} {value!r} (from {source}) is not {RELATIVE_PATH_RULE}")
    return tuple(parts)


def resolve_under(root: str | Path, value: object, what: str, source: str) -> Path:
    """``root / value`` for ``value`` a path relative to ``root`` (:func:`relative_parts`), checked
    by :func:`join_under`: symlinks resolved, it must lie under ``root``. An absolute ``value``
    or one with a ``..`` part is an :class:`UnsafePathError` naming it and ``source``."""
    parts = relative_parts(value, what, source)
    return join_under(root, *((part, what) for part in parts), source=source)


_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
)


def regular_file(path: str | Path, what: str) -> Path:
    """``path`` if it is a regular file (symlinks followed). Reading a device (``/dev/zero``), a
    FIFO or a socket may never end, so any of those (or a folder) is an :class:`UnsafePathError`
    naming ``what`` and the path; a missing one is a ``FileNotFoundError``."""
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        kind = next((name for test, name in _KINDS if test(mode)), "a special file")
        raise UnsafePathError(f"{what} {path} is {kind}, not a regular file")
    return Path(path)

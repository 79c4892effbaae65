"""Names from data, configs and flags that become one path component, kept inside their root.

A ``frame_id``, a sequence name, an attack ``VARIANT``, ``--extra_tag`` or ``--eval_tag`` names
one file or folder under a root the user chose. :func:`safe_component` admits only such a name
(``../../x``, ``..`` or ``a/b`` would leave the root); :func:`join_under` joins several and
checks the result, symlinks resolved, still lies under the root.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["SAFE_COMPONENT_RULE", "UnsafePathError", "join_under", "safe_component"]

_SAFE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
SAFE_COMPONENT_RULE = (
    "one file or folder name of letters, digits, '.', '_' and '-' that starts with a letter or "
    "digit (no '/', not '.' or '..')"
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

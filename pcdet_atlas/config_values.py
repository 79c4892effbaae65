"""Typed, checked reads of attack-config values (errors name the key, the value and the file).

``check_known_keys`` rejects unknown keys; this module does the same for bad values of known
keys, so that ``SEED: abc`` or ``P_DUAL: 2`` fail with a :class:`~pcdet_atlas.config.ConfigError`
such as ``P_DUAL = 2.0 (from cfgs/attacks/my.yaml): expected a probability in [0, 1]`` instead of
a bare ``ValueError`` from deep inside a constructor.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from pcdet_atlas.config import ConfigError, key_source
from pcdet_atlas.utils.common import resolve_device

__all__ = ["config_value", "config_error", "config_files", "check_finite", "config_device"]

_REQUIRED = object()


def config_files(node: Mapping) -> str:
    """The files the keys of a loaded config node came from, comma-separated."""
    files = sorted({key_source(node, k) for k in node} - {"<unknown>"})
    return ", ".join(files) or "<unknown>"


def config_error(node: Mapping, key: str, section: str, expected: str) -> ConfigError:
    """A :class:`ConfigError` naming ``section.key``, its value, its file and what was expected."""
    where = f"{section}.{key}" if section else key
    value = node.get(key) if hasattr(node, "get") else None
    return ConfigError(f"{where} = {value!r} (from {key_source(node, key)}): expected {expected}")


def config_value(
    node: Mapping,
    key: str,
    cast: Callable[[Any], Any],
    section: str = "",
    default: Any = _REQUIRED,
    valid: Callable[[Any], bool] | None = None,
    expected: str | None = None,
) -> Any:
    """``cast(node[key])`` (or ``default`` when the key is absent), checked by ``valid``.

    Args:
        node: a loaded config node (``EasyDict`` from :func:`cfg_from_yaml_file`, or a dict).
        key: the key to read. cast: e.g. ``int``, ``float``, ``str``.
        section: dotted name of the node for messages (``''`` for the top level).
        default: value when the key is absent; without it the key is required.
        valid: predicate on the cast value. expected: what a valid value is, for the message.
    Raises:
        ConfigError: naming the key, the value, the file and ``expected``.
    """
    expected = expected or f"a value of type {getattr(cast, '__name__', cast)}"
    if key not in node:
        if default is _REQUIRED:
            where = f"{section}.{key}" if section else key
            raise ConfigError(f"missing required key {where} (in {config_files(node)})")
        return default
    raw = node[key]
    if isinstance(raw, bool) and cast in (int, float):
        raise config_error(node, key, section, expected)
    if cast is int and isinstance(raw, float):  # SEED: 1.7 is no seed, and 2.0 is a typo too
        raise config_error(node, key, section, f"{expected} (an integer, not a float)")
    try:
        value = cast(raw)
    except (TypeError, ValueError) as err:
        raise config_error(node, key, section, expected) from err
    if isinstance(value, float) and not math.isfinite(value):
        raise config_error(node, key, section, f"{expected} (a finite number)")
    if valid is not None and not valid(value):
        raise config_error(node, key, section, expected)
    return value


def check_finite(node: Mapping, section: str = "") -> None:
    """Raise :class:`ConfigError` at the first NaN or infinite float anywhere under ``node``
    (nested sections and lists included), naming its dotted key and file."""
    for key, value in node.items():
        where = f"{section}.{key}" if section else str(key)
        _check_finite_value(value, node, key, where)


def _check_finite_value(value: Any, node: Mapping, key: str, where: str) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(
            f"{where} = {value!r} (from {key_source(node, key)}): expected a finite number"
        )
    if isinstance(value, Mapping):
        check_finite(value, where)
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _check_finite_value(item, node, key, f"{where}[{i}]")


def config_device(node: Mapping, key: str = "DEVICE", default: str = "cpu") -> str:
    """The torch device named by ``node[key]``, checked to exist on this machine
    (:func:`~pcdet_atlas.utils.common.resolve_device`)."""
    name = config_value(node, key, str, default=default, expected="a torch device such as 'cpu'")
    try:
        resolve_device(name)
    except ValueError as err:
        raise config_error(node, key, "", f"a device this machine has ({err})") from None
    return name

"""Typed, checked reads of config sections (errors name the file, the key, the value and what
was expected).

A config section is declared once, as a frozen dataclass whose fields come from :func:`setting`
(type from the annotation; default, bounds, choices and meaning from the setting), and read by
one helper, :func:`read_section`, as detectron2's ``@configurable`` reads a declared signature::

    @dataclass(frozen=True, kw_only=True)
    class TrackingConfig:
        dt: float = setting(0.1, gt=0, doc="s per frame")

    read_section(TrackingConfig, cfg.TRACKING, "TRACKING")  # -> TrackingConfig(dt=0.1)

An unknown key, a value of the wrong type or out of range, and a missing required key each fail
with one :class:`~pcdet_atlas.config.ConfigError` such as
``P_DUAL = 2.0 (from cfgs/attacks/my.yaml): expected a number >= 0 and <= 1`` instead of a bare
``ValueError`` from deep inside a constructor; docs' key tables are checked against
:func:`declared_keys`. :func:`config_value` reads one value the same way, for the few keys a
declaration does not fit.
"""

from __future__ import annotations

import collections.abc
import dataclasses
import math
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from pcdet_atlas.config import ConfigError, check_known_keys, key_source
from pcdet_atlas.utils.common import resolve_device

__all__ = [
    "config_value",
    "config_error",
    "config_files",
    "check_finite",
    "config_device",
    "REQUIRED",
    "setting",
    "section",
    "unsupported",
    "read_section",
    "declared_keys",
    "declared_defaults",
    "declared_settings",
    "fields_of",
    "as_lists",
    "is_declaration",
]

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


# ------------------------------------------------------------------ declared sections
#: ``setting()`` without a default: the key is required.
REQUIRED: Any = dataclasses.MISSING
_META = "pcdet_atlas.setting"


@dataclasses.dataclass(frozen=True)
class Setting:
    """What a declaration field says about its config key (see :func:`setting`)."""

    key: str | None
    doc: str
    ge: float | None
    gt: float | None
    le: float | None
    lt: float | None
    choices: tuple | None
    length: int | None
    check: Callable[[Any], bool] | None
    expected: str | None


def setting(
    default: Any = REQUIRED,
    *,
    doc: str = "",
    key: str | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: Iterable | None = None,
    length: int | None = None,
    check: Callable[[Any], bool] | None = None,
    expected: str | None = None,
    default_factory: Callable[[], Any] | None = None,
    compare: bool = True,
) -> Any:
    """One key of a config declaration (a field of a ``@dataclass(frozen=True, kw_only=True)``
    read by :func:`read_section`); its type is the field's annotation.

    Args:
        default: the value when the key is absent (:data:`REQUIRED`: the key must be given).
        doc: what the key means, with its unit.
        key: the YAML key (default: the field's name upper-cased, e.g. ``p_dual`` -> ``P_DUAL``).
        ge, gt, le, lt: bounds of a number (of every element of a list of numbers).
        choices: the values allowed (of every element of a list).
        length: the number of elements of a list.
        check: a predicate on the whole (converted) value, e.g. ``lo <= hi`` of a pair.
        expected: what a valid value is, for the message (built from the rest when omitted).
        default_factory: builds the default (a nested section's defaults, a list).
        compare: whether the field takes part in ``==`` (as :func:`dataclasses.field`'s).
    """
    meta = Setting(
        key, doc, ge, gt, le, lt, None if choices is None else tuple(choices), length, check,
        expected,
    )  # fmt: skip
    if default_factory is not None:
        return dataclasses.field(
            default_factory=default_factory, compare=compare, metadata={_META: meta}
        )
    return dataclasses.field(default=default, compare=compare, metadata={_META: meta})


def section(decl: type, doc: str = "", key: str | None = None) -> Any:
    """A nested section declared by ``decl``: every key at its default when absent."""
    return setting(default_factory=decl, doc=doc, key=key)


def unsupported(why: str) -> Any:
    """A boolean key accepted for OpenPCDet's configs that must stay False (``why``: what is
    not supported, for the message)."""
    return setting(False, check=_is_false, expected=f"False ({why})", doc=f"must be False: {why}")


def _is_false(value: bool) -> bool:
    return value is False


def is_declaration(obj: Any) -> bool:
    """Whether ``obj`` is a config declaration class (a dataclass of :func:`setting` fields)."""
    return isinstance(obj, type) and dataclasses.is_dataclass(obj)


def _settings(decl: type) -> list[tuple[dataclasses.Field, Setting, str, Any]]:
    """``(field, setting, YAML key, type)`` of every field of ``decl``, in declaration order."""
    hints = typing.get_type_hints(decl)
    out = []
    for f in dataclasses.fields(decl):
        meta = f.metadata.get(_META) or Setting(None, "", *([None] * 8))
        out.append((f, meta, meta.key or f.name.upper(), hints[f.name]))
    return out


def declared_keys(decl: type, prefix: str = "") -> list[str]:
    """Every key ``decl`` accepts, dotted through nested sections (``GROUND.RADIUS``); a
    section also names itself (``GROUND``)."""
    keys = []
    for _, _, key, kind in _settings(decl):
        dotted = f"{prefix}{key}"
        keys.append(dotted)
        nested = _section_type(kind)
        if nested is not None:
            keys += declared_keys(nested, f"{dotted}.")
    return keys


def declared_defaults(decl: type) -> dict[str, Any]:
    """``{field name: default}`` of the fields of ``decl`` that have one (nested sections as
    their declaration's defaults)."""
    out = {}
    for f in dataclasses.fields(decl):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


def declared_settings(decl: type, prefix: str = "") -> list[tuple[str, Any, str]]:
    """``(dotted key, default or REQUIRED, doc)`` of every key of ``decl`` (nested sections
    expanded), for a docs table."""
    rows = []
    for f, meta, key, kind in _settings(decl):
        nested = _section_type(kind)
        if nested is not None:
            rows += declared_settings(nested, f"{prefix}{key}.")
            continue
        default = f.default
        if f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        rows.append((f"{prefix}{key}", default, meta.doc))
    return rows


def as_lists(value: Any) -> Any:
    """A read value with its tuples (nested ones too) as the lists YAML gave, for constructors
    that keep a list as they got it."""
    if isinstance(value, (tuple, list)):
        return [as_lists(v) for v in value]
    return value


def fields_of(decl: Any) -> dict[str, Any]:
    """``{field name: value}`` of a read declaration (shallow: nested sections stay objects),
    to pass as keyword arguments."""
    return {f.name: getattr(decl, f.name) for f in dataclasses.fields(decl)}


def read_section(
    decl: type,
    node: Mapping | None,
    section: str = "",
    *,
    where: str | None = None,
    ignore: Iterable[str] = (),
) -> Any:
    """Read a config section into the declaration ``decl`` (an instance of it).

    Every key of ``node`` must be declared (or listed in ``ignore``: keys another reader owns);
    every value is checked against its field's type, bounds and choices; absent keys take the
    declared default, and a required key that is absent is an error. ``None`` reads as an empty
    section.

    Args:
        decl: the declaration class. node: the loaded section (``EasyDict`` or a dict).
        section: dotted path of ``node`` in its file (``'MODEL.DENSE_HEAD'``; ``''`` at the top),
            prefixed to every key in messages.
        where: how messages name the section (default: ``section``), e.g. ``'attack config
            InjectionAttack'``.
    Raises:
        ConfigError: naming the file(s), the full key path, the bad value and what was expected.
    """
    where = where or section or "the config"
    node = {} if node is None else node
    if not isinstance(node, Mapping):
        raise ConfigError(f"{where} = {node!r}: expected a section (a mapping of keys)")
    settings = _settings(decl)
    check_known_keys(node, [key for _, _, key, _ in settings] + list(ignore), where)
    values = {}
    for f, meta, key, kind in settings:
        dotted = f"{section}.{key}" if section else key
        if key not in node:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                place = f" in {where}" if where != (section or "the config") else ""
                raise ConfigError(f"missing required key {dotted}{place} (in {config_files(node)})")
            continue
        # an item of a list keeps no file of its own: name its place (which names the file)
        origin = key_source(node, key)
        if origin == "<unknown>" and where != (section or "the config"):
            origin = where
        values[f.name] = _read_value(node, key, dotted, kind, meta, origin)
    try:
        return decl(**values)
    except ConfigError:
        raise
    except ValueError as err:  # a check across keys, in the declaration's __post_init__
        raise ConfigError(f"{where} (from {config_files(node)}): {err}") from err


def _section_type(kind: Any) -> type | None:
    """The declaration of a nested-section type (``Decl`` or ``Decl | None``), else None."""
    if is_declaration(kind):
        return kind
    args = [a for a in typing.get_args(kind) if a is not type(None)]
    if _is_union(kind) and len(args) == 1 and is_declaration(args[0]):
        return args[0]
    return None


def _is_union(kind: Any) -> bool:
    return typing.get_origin(kind) in (typing.Union, types.UnionType)


def _read_value(node: Mapping, key: str, dotted: str, kind: Any, meta: Setting, origin: str) -> Any:
    raw = node[key]

    def fail(what: str | None = None) -> ConfigError:
        expected = meta.expected or _describe(kind, meta)
        return ConfigError(
            f"{dotted} = {raw!r} (from {origin}): expected {expected}{f' ({what})' if what else ''}"
        )

    nested = _section_type(kind)
    if nested is not None:
        if raw is None and _is_union(kind):
            return None
        if raw is not None and not isinstance(raw, Mapping):
            raise fail()
        return read_section(nested, raw, dotted)
    try:
        value = _convert(raw, kind)
    except _NotFinite:
        raise fail("a finite number") from None
    except (TypeError, ValueError):
        raise fail() from None
    if value is not None and not _within(value, meta):
        raise fail()
    return value


class _NotFinite(ValueError):
    pass


def _convert(raw: Any, kind: Any) -> Any:
    """``raw`` as ``kind`` (int, float, bool, str, tuple/list of those, ``X | None``, Any,
    dict/Mapping), or TypeError/ValueError."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if kind is Any:
        return raw
    if _is_union(kind):
        if raw is None and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(raw, arg)
            except _NotFinite:
                raise
            except (TypeError, ValueError):
                continue
        raise TypeError(raw)
    if kind is bool:
        if not isinstance(raw, bool):
            raise TypeError(raw)
        return raw
    if kind is int:
        if isinstance(raw, bool) or not isinstance(raw, int):
            raise TypeError(raw)  # SEED: 1.7 is no seed, and 2.0 is a typo too
        return int(raw)
    if kind is float:
        if isinstance(raw, bool) or not isinstance(raw, (int, float)):
            raise TypeError(raw)
        if not math.isfinite(raw):
            raise _NotFinite(raw)
        return float(raw)
    if kind is str:
        if not isinstance(raw, str):
            raise TypeError(raw)
        return raw
    if kind in (dict, Mapping) or origin in (dict, Mapping, collections.abc.Mapping):
        if not isinstance(raw, Mapping):
            raise TypeError(raw)
        return raw
    if origin in (tuple, list):
        if not isinstance(raw, (list, tuple)):
            raise TypeError(raw)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(raw) != len(args):
                raise ValueError(raw)
            return tuple(_convert(v, a) for v, a in zip(raw, args, strict=True))
        item = args[0] if args else Any
        return origin(_convert(v, item) for v in raw)
    raise TypeError(f"cannot read a config value as {kind!r}")


def _numbers(value: Any) -> list:
    if isinstance(value, (list, tuple)):
        return [x for v in value for x in _numbers(v)]
    return [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else []


def _within(value: Any, meta: Setting) -> bool:
    numbers = _numbers(value)
    bounds = (
        (meta.ge, lambda x, b: x >= b),
        (meta.gt, lambda x, b: x > b),
        (meta.le, lambda x, b: x <= b),
        (meta.lt, lambda x, b: x < b),
    )
    for bound, ok in bounds:
        if bound is not None and not all(ok(x, bound) for x in numbers):
            return False
    if meta.choices is not None:
        items = value if isinstance(value, (list, tuple)) else [value]
        if not all(v in meta.choices for v in items):
            return False
    if meta.length is not None and len(value) != meta.length:
        return False
    return meta.check is None or bool(meta.check(value))


_NAMES = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def _describe(kind: Any, meta: Setting | None = None) -> str:
    """What a valid value is, from the type and the bounds (``'a number in [0, 1]'``)."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    others = [a for a in args if a is not type(None)]
    if _is_union(kind) and len(others) == 1:
        return f"{_describe(others[0], meta)} or null"
    if _is_union(kind):
        text = " or ".join(_describe(a) for a in others) + (" or null" if others != args else "")
    elif origin in (tuple, list):
        if origin is tuple and args and args[-1] is not Ellipsis and len(set(args)) == 1:
            text = f"a list of {len(args)} {_plural(_describe(args[0]))}"
        elif origin is tuple and args and args[-1] is not Ellipsis:
            text = f"a list [{', '.join(_describe(a) for a in args)}]"
        else:
            count = f"{meta.length} " if meta and meta.length is not None else ""
            text = f"a list of {count}{_plural(_describe(args[0]) if args else 'values')}"
    elif kind in (dict, Mapping) or origin in (dict, Mapping, collections.abc.Mapping):
        text = "a mapping"
    else:
        text = _NAMES.get(kind, getattr(kind, "__name__", str(kind)))
    if meta is None:
        return text
    low = ("[", meta.ge) if meta.ge is not None else ("(", meta.gt)
    high = ("]", meta.le) if meta.le is not None else (")", meta.lt)
    if low[1] is not None and high[1] is not None:
        text += f" in {low[0]}{low[1]:g}, {high[1]:g}{high[0]}"
    elif low[1] is not None:
        text += f" {'>=' if low[0] == '[' else '>'} {low[1]:g}"
    elif high[1] is not None:
        text += f" {'<=' if high[0] == ']' else '<'} {high[1]:g}"
    if meta.choices is not None:
        choices = ", ".join(map(repr, meta.choices))
        text = f"one of {choices}" if kind is str else f"{text} (each one of {choices})"
    return text


def _plural(text: str) -> str:
    for article in ("an ", "a "):
        if text.startswith(article):
            head, _, rest = text[len(article) :].partition(" ")
            return f"{head}s{' ' + rest if rest else ''}"
    return text

"""YAML configs with OpenPCDet's structure and merge semantics, without a global ``cfg``.

Differences from OpenPCDet, on purpose:

* ``_BASE_CONFIG_`` resolves relative to the file that names it (then, for OpenPCDet-style paths
  such as ``cfgs/dataset_configs/x.yaml``, relative to the repository root), never the working
  directory; bases may themselves have bases; a missing base is an error naming both files.
* every key remembers the file it came from, so consumers can reject unknown keys with an error
  naming the key and the file (:func:`check_known_keys`).
* :func:`cfg_from_yaml_file` returns a new object; nothing is global.

Merge rules are OpenPCDet's: the base is loaded first, then the including file's keys override it;
dicts merge recursively, every other value (lists included) replaces the old one wholesale.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml
from easydict import EasyDict

from pcdet_atlas.utils.files import write_atomic

BASE_KEY = "_BASE_CONFIG_"
REPO_ROOT = Path(__file__).resolve().parent.parent
_SOURCES_ATTR = "_key_sources"


def resolve_repo_path(path: str | Path) -> Path:
    """A path from a config (``DATA_PATH``, an RPN's ``CFG`` / ``CHECKPOINT``, also when given
    with ``--set``): absolute as given, else relative to the repository root, whatever the
    working directory."""
    path = Path(path).expanduser()
    return path if path.is_absolute() else (REPO_ROOT / path).resolve()


def resolve_cli_path(path: str | Path) -> Path:
    """A path typed as a tool's option (``--data_path``, ``--out_dir``, ...): absolute as given,
    else relative to the working directory, as any shell command reads it. Tools resolve it
    before it enters a config, where :func:`resolve_repo_path` would read it otherwise."""
    return Path(path).expanduser().resolve()


def repo_relative(path: str | Path) -> Path:
    """``path`` relative to the repository root when it lies inside it (absolute otherwise), as
    reports and ``results.json`` name configs and files, independent of where the clone is."""
    path = Path(path).resolve()
    return path.relative_to(REPO_ROOT) if path.is_relative_to(REPO_ROOT) else path


class ConfigError(ValueError):
    """A config that cannot be loaded, merged or overridden as asked."""


def _set_source(node: EasyDict, key: str, source: str) -> None:
    sources = getattr(node, _SOURCES_ATTR, None)
    if sources is None:
        sources = {}
        object.__setattr__(node, _SOURCES_ATTR, sources)
    sources[key] = source


def key_source(node: Mapping, key: str) -> str:
    """The file a key of a loaded config node came from (``'<unknown>'`` for hand-built dicts)."""
    return getattr(node, _SOURCES_ATTR, {}).get(key, "<unknown>")


def _resolve_base(base: str, including_file: Path) -> Path:
    candidate = Path(base)
    if candidate.is_absolute():
        tried = [candidate]
    else:
        tried = [including_file.parent / candidate, REPO_ROOT / candidate]
    for path in tried:
        if path.is_file():
            return path.resolve()
    raise ConfigError(
        f"{including_file}: {BASE_KEY} {base!r} not found (looked at "
        f"{', '.join(str(p) for p in tried)})"
    )


def _load_yaml(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    with open(path) as f:
        try:
            data = yaml.safe_load(f)
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: invalid YAML: {err}") from err
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data


def merge_new_config(
    config: EasyDict, new_config: Mapping, source: Path, _stack: tuple[Path, ...] = ()
) -> EasyDict:
    """Merge ``new_config`` (read from ``source``) into ``config`` in place; returns ``config``."""
    if BASE_KEY in new_config:
        base_path = _resolve_base(str(new_config[BASE_KEY]), source)
        if base_path in _stack or base_path == source:
            chain = " -> ".join(str(p) for p in (*_stack, source, base_path))
            raise ConfigError(f"{BASE_KEY} cycle: {chain}")
        merge_new_config(config, _load_yaml(base_path), base_path, (*_stack, source))
    for key, val in new_config.items():
        if key == BASE_KEY:
            continue
        if isinstance(val, Mapping):
            if not isinstance(config.get(key), Mapping):
                config[key] = EasyDict()
            merge_new_config(config[key], val, source, _stack)
        else:
            config[key] = val
        _set_source(config, key, str(source))
    return config


def cfg_from_yaml_file(cfg_file: str | Path) -> EasyDict:
    """Load a YAML config with its ``_BASE_CONFIG_`` chain into a new :class:`EasyDict`."""
    path = Path(cfg_file).resolve()
    return merge_new_config(EasyDict(), _load_yaml(path), path)


def _cast_like(text: str, old: Any, where: str) -> Any:
    if isinstance(old, bool):
        if text.lower() in ("true", "1"):
            return True
        if text.lower() in ("false", "0"):
            return False
        raise ConfigError(f"{where}: expected bool, got {text!r}")
    try:
        return type(old)(text)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where}: cannot convert {text!r} to {type(old).__name__}") from err


def cfg_from_list(cfg_list: list[str], config: EasyDict) -> EasyDict:
    """Apply ``--set A.B value ...`` overrides in place, with OpenPCDet's typing rules.

    Every key must exist. The value is parsed with :func:`ast.literal_eval` (a string if that
    fails) and must have the old value's type, except: a dict target takes ``'k1:v1,k2:v2'``
    (each cast to the old entry's type); a list target takes a comma string cast elementwise to
    the type of the old first element; a ``None`` target takes any value.
    """
    if len(cfg_list) % 2 != 0:
        raise ConfigError(f"--set expects KEY VALUE pairs, got an odd number of items: {cfg_list}")
    for dotted, text in zip(cfg_list[0::2], cfg_list[1::2]):
        node: Any = config
        parts = dotted.split(".")
        for depth, part in enumerate(parts[:-1]):
            if not isinstance(node, Mapping) or part not in node:
                raise ConfigError(f"--set {dotted}: key {'.'.join(parts[: depth + 1])!r} not found")
            node = node[part]
        last = parts[-1]
        if not isinstance(node, Mapping) or last not in node:
            raise ConfigError(f"--set {dotted}: key {dotted!r} not found")
        old = node[last]
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text
        if old is None or type(value) is type(old):
            node[last] = value
        elif isinstance(old, Mapping):
            for item in str(text).split(","):
                if ":" not in item:
                    raise ConfigError(f"--set {dotted}: expected 'key:value,...', got {text!r}")
                sub_key, sub_val = item.split(":", 1)
                if sub_key not in old:
                    raise ConfigError(f"--set {dotted}: key {dotted}.{sub_key} not found")
                old[sub_key] = _cast_like(sub_val, old[sub_key], f"--set {dotted}.{sub_key}")
        elif isinstance(old, list):
            items = value if isinstance(value, (list, tuple)) else str(text).split(",")
            elem = old[0] if old else None
            node[last] = [
                x if elem is None else _cast_like(str(x), elem, f"--set {dotted}") for x in items
            ]
        else:
            raise ConfigError(
                f"--set {dotted}: type {type(value).__name__} ({text!r}) does not match the "
                f"original type {type(old).__name__} ({old!r})"
            )
        _set_source(node, last, "--set")
    return config


def check_known_keys(node: Mapping, allowed: Iterable[str], section: str) -> None:
    """Raise :class:`ConfigError` if ``node`` has a key outside ``allowed``.

    The message names the key, the section, the file it came from and the allowed keys.
    """
    allowed = set(allowed)
    for key in node:
        if key not in allowed:
            raise ConfigError(
                f"unknown key {key!r} in {section} (from {key_source(node, key)}); "
                f"allowed keys: {', '.join(sorted(allowed))}"
            )


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _is_str_list(v: Any) -> bool:
    return isinstance(v, (list, tuple)) and len(v) > 0 and all(isinstance(x, str) for x in v)


#: The sections of a detector config (``tools/train.py`` / ``tools/test.py``); the nested keys of
#: each are checked by the code that reads the section.
EXPERIMENT_SECTIONS = ("CLASS_NAMES", "DATA_CONFIG", "MODEL", "OPTIMIZATION", "ATLAS", "STAGE")
#: ``(dotted key, check, what a valid value is)`` of the values whose type is checked at load time.
EXPERIMENT_VALUES: tuple[tuple[str, Callable[[Any], bool], str], ...] = (
    ("CLASS_NAMES", _is_str_list, "a non-empty list of class names, e.g. [Vehicle]"),
    ("DATA_CONFIG", lambda v: isinstance(v, Mapping), "a section (a mapping of keys)"),
    ("MODEL", lambda v: isinstance(v, Mapping), "a section (a mapping of keys)"),
    ("OPTIMIZATION", lambda v: isinstance(v, Mapping), "a section (a mapping of keys)"),
    ("ATLAS", lambda v: isinstance(v, Mapping), "a section (a mapping of keys)"),
    (
        "DATA_CONFIG.POINT_CLOUD_RANGE",
        lambda v: (
            isinstance(v, (list, tuple))
            and len(v) == 6
            and all(map(_is_number, v))
            and all(v[i] < v[i + 3] for i in range(3))
        ),
        "6 finite numbers [x_min, y_min, z_min, x_max, y_max, z_max] with min < max (m)",
    ),
)


def check_experiment_config(cfg: Mapping) -> None:
    """Raise :class:`ConfigError` for an unknown top-level section of a detector config (e.g. a
    misspelt ``OPTIMISATION``) or a value of the wrong type in :data:`EXPERIMENT_VALUES`,
    naming the key, the value and the file it came from."""
    check_known_keys(cfg, EXPERIMENT_SECTIONS, "the detector config")
    for dotted, valid, expected in EXPERIMENT_VALUES:
        *parents, key = dotted.split(".")
        node = cfg
        for name in parents:
            node = node.get(name) if isinstance(node, Mapping) else None
        if not isinstance(node, Mapping) or key not in node:
            continue  # a missing key is reported by the code that needs it
        if not valid(node[key]):
            raise ConfigError(
                f"{dotted} = {node[key]!r} (from {key_source(node, key)}): expected {expected}"
            )


def require_keys(node: Mapping, required: Iterable[str], section: str) -> None:
    """Raise :class:`ConfigError` naming the first of ``required`` missing from ``node``."""
    for key in required:
        if key not in node:
            origin = {key_source(node, k) for k in node} - {"<unknown>"}
            where = f" ({', '.join(sorted(origin))})" if origin else ""
            raise ConfigError(f"missing required key {key!r} in {section}{where}")


def to_plain(obj: Any) -> Any:
    """Recursively turn EasyDicts/tuples/numpy scalars into plain YAML-safe Python values."""
    if isinstance(obj, Mapping):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item) and getattr(obj, "ndim", 1) == 0:
        return obj.item()
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def save_config(cfg: Mapping, path: str | Path) -> Path:
    """Write the fully merged config as YAML (the file saved beside every output), whole
    (:func:`~pcdet_atlas.utils.files.write_atomic`): a symlink at ``path`` in a received output
    folder is replaced, not written through."""
    text = yaml.safe_dump(to_plain(cfg), sort_keys=False)
    return write_atomic(path, lambda f: f.write(text.encode()))


def log_config_to_file(cfg: Mapping, logger, pre: str = "cfg") -> None:
    """Log every leaf as ``pre.KEY: value`` (OpenPCDet's habit)."""
    for key, val in cfg.items():
        if isinstance(val, Mapping):
            log_config_to_file(val, logger, pre=f"{pre}.{key}")
        else:
            logger.info(f"{pre}.{key}: {val}")

"""Name -> class registries for datasets, transforms, attacks, detectors and model stages.

Adding a component is one decorated class in one new file::

    from pcdet_atlas.registry import ATTACKS

    @ATTACKS.register()
    class MyAttack:
        ...

Registering the same name twice raises; looking up an unknown name raises with the list of the
known names. Each registry knows which package defines its built-in members and imports it on the
first lookup, so ``DATASETS.get('WaymoDataset')`` works without importing anything first.
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

T = TypeVar("T")


class RegistryError(KeyError):
    """An unknown or duplicate registry name."""

    def __str__(self) -> str:  # KeyError quotes its message; show it plainly
        return str(self.args[0]) if self.args else ""


def _describe(obj: Any) -> str:
    """``module.QualName`` of a registered class or function; for an instance (an analysis, a
    confidence kind), that of its class."""
    qualname = getattr(obj, "__qualname__", None)
    if qualname is None:
        return f"an instance of {type(obj).__module__}.{type(obj).__qualname__}"
    return f"{getattr(obj, '__module__', '?')}.{qualname}"


class Registry:
    """A named mapping from string keys to classes (or factory functions)."""

    def __init__(self, name: str, autoload: tuple[str, ...] = ()):
        """
        Args:
            name: what the registry holds, used in error messages (e.g. ``'attack'``).
            autoload: modules imported on the first lookup, where the built-ins register.
        """
        self.name = name
        self._autoload = tuple(autoload)
        self._loaded = not self._autoload
        self._items: dict[str, Any] = {}

    def register(self, name: str | None = None) -> Callable[[T], T]:
        """Decorator registering a class or function as ``name`` (default: its ``__name__``)."""

        def decorator(obj: T) -> T:
            key = name or obj.__name__
            if key in self._items and self._items[key] is not obj:
                raise RegistryError(
                    f"{self.name} registry: name {key!r} is already registered to "
                    f"{_describe(self._items[key])}; cannot register {_describe(obj)} under the "
                    "same name"
                )
            self._items[key] = obj
            return obj

        return decorator

    def _ensure_loaded(self) -> None:
        if self._loaded:
            return
        self._loaded = True
        for module in self._autoload:
            importlib.import_module(module)

    def get(self, name: str) -> Any:
        """Return the object registered as ``name``; raise with the known names if there is none."""
        self._ensure_loaded()
        if name not in self._items:
            known = sorted(self._items)
            close = difflib.get_close_matches(str(name), known, n=3)
            hint = f" Did you mean {', '.join(map(repr, close))}?" if close else ""
            raise RegistryError(
                f"unknown {self.name} {name!r}. Known {self.name} names: "
                f"{', '.join(known) if known else '(none)'}.{hint}"
            )
        return self._items[name]

    def list(self) -> list[str]:
        """Sorted names of everything registered."""
        self._ensure_loaded()
        return sorted(self._items)

    def items(self) -> list[tuple[str, Any]]:
        """``(name, object)`` of everything registered, in the order it registered (where the
        order means something, e.g. the keys an analysis adds to a ``results.json`` entry)."""
        self._ensure_loaded()
        return list(self._items.items())

    def unregister(self, name: str) -> Any:
        """Remove ``name`` and return what it held (a test undoing its registration); an unknown
        name raises as :meth:`get` does."""
        obj = self.get(name)
        del self._items[name]
        return obj

    def __contains__(self, name: object) -> bool:
        self._ensure_loaded()
        return name in self._items

    def __iter__(self) -> Iterator[str]:
        return iter(self.list())

    def __len__(self) -> int:
        self._ensure_loaded()
        return len(self._items)

    def registered_now(self) -> frozenset[str]:
        """The names registered so far, without importing the built-ins (what a plugin module
        adds is the difference before and after its import)."""
        return frozenset(self._items)

    def __repr__(self) -> str:
        return f"Registry({self.name!r}, items={self.list()})"


DATASETS = Registry("dataset", autoload=("pcdet_atlas.datasets", "pcdet_atlas.attacks"))
TRANSFORMS = Registry("transform", autoload=("pcdet_atlas.datasets",))
ATTACKS = Registry("attack", autoload=("pcdet_atlas.attacks",))
DETECTORS = Registry("detector", autoload=("pcdet_atlas.models",))
MODEL_STAGES = Registry("model stage", autoload=("pcdet_atlas.models",))
#: the evaluation's analyses (pcdet_atlas.evaluation.analyses.register_analysis) and the
#: confidence kinds an attack family may name (register_confidence_kind)
ANALYSES = Registry("analysis", autoload=("pcdet_atlas.evaluation.analyses",))
CONFIDENCE_KINDS = Registry("confidence kind", autoload=("pcdet_atlas.evaluation.analyses",))

#: every registry a plugin module (``--plugin``, :func:`pcdet_atlas.utils.cli.import_plugins`)
#: may add to, by the kind of component it holds
REGISTRIES: dict[str, Registry] = {
    "dataset": DATASETS,
    "transform": TRANSFORMS,
    "attack": ATTACKS,
    "detector": DETECTORS,
    "model stage": MODEL_STAGES,
    "analysis": ANALYSES,
    "confidence kind": CONFIDENCE_KINDS,
}

"""What every model stage's config section holds: its registered ``NAME`` (each stage declares
the rest in a subclass of :class:`StageConfig`, read by :func:`read_stage`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pcdet_atlas.config_values import read_section, setting

__all__ = ["StageConfig", "read_stage"]


@dataclass(frozen=True, kw_only=True)
class StageConfig:
    """The keys of every ``MODEL.<STAGE>`` section."""

    name: str | None = setting(None, doc="registered stage class")


def read_stage(cls: type, cfg: Mapping, section: str) -> Any:
    """``cfg`` (the ``MODEL.<STAGE>`` section ``section``) read into ``cls.CONFIG``."""
    return read_section(cls.CONFIG, cfg, section)

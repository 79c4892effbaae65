"""OpenPCDet's own models under attack, on the fly: any architecture OpenPCDet builds.

Where OpenPCDet (the ``pcdet`` package) is importable, importing this package registers
:class:`~pcdet_atlas.integrations.openpcdet.dataset.AtlasWaymoDataset` in OpenPCDet's dataset
registry (``pcdet.datasets.__all__``) as ``'AtlasWaymoDataset'``: an OpenPCDet
``DATA_CONFIG`` with ``DATASET: AtlasWaymoDataset`` and ``ATLAS_ATTACK: <attack YAML>`` serves
that ATLAS variant of OpenPCDet's Waymo infos to OpenPCDet's own loader and models.
:func:`~pcdet_atlas.integrations.openpcdet.evaluate.evaluate_openpcdet`
(``tools/openpcdet_test.py``) runs an OpenPCDet checkpoint on every variant and writes
``results.json``.

Where it is not importable, this package still imports (so ``--help`` and the docs work) and
:func:`require_openpcdet` names the import error. Supported: OpenPCDet 0.6.0 (the interfaces
this package touches are those of open-mmlab/OpenPCDet at commit :data:`OPENPCDET_COMMIT`;
docs/benchmark_your_detector.md).
"""

from __future__ import annotations

__all__ = ["OPENPCDET_COMMIT", "OpenPCDetMissingError", "require_openpcdet"]

#: the OpenPCDet commit (v0.6.0) whose interfaces this integration and its stand-in test mirror
OPENPCDET_COMMIT = "8cacccec11db6f59bf6934600c9a175dae254806"


class OpenPCDetMissingError(ImportError):
    """OpenPCDet is not importable here."""


try:
    import pcdet.datasets  # noqa: F401 - only whether OpenPCDet imports, and its error if not
except ImportError as err:  # OpenPCDet absent, or its compiled ops not built for this machine
    _IMPORT_ERROR: ImportError | None = err
else:
    _IMPORT_ERROR = None

if _IMPORT_ERROR is None:
    from pcdet_atlas.integrations.openpcdet.dataset import AtlasWaymoDataset, register
    from pcdet_atlas.integrations.openpcdet.evaluate import evaluate_openpcdet

    __all__ += ["AtlasWaymoDataset", "evaluate_openpcdet", "register"]
    register()


def require_openpcdet() -> None:
    """Raise :class:`OpenPCDetMissingError` naming why ``pcdet`` did not import."""
    if _IMPORT_ERROR is not None:
        raise OpenPCDetMissingError(
            f"OpenPCDet is not importable ({type(_IMPORT_ERROR).__name__}: {_IMPORT_ERROR}); "
            "install OpenPCDet 0.6.0 (python setup.py develop in its clone, with its CUDA ops) "
            "in this environment"
        )

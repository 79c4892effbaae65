"""The package's layers import only downward (checked on the source with ``ast``, no importing).

bottom (config, config_values, registry, utils, ops, version) <- evaluation <- datasets
<- attacks, models <- train_utils. Datasets may call the Waymo metric (OpenPCDet's
``dataset.evaluation``); models read dataset configs; neither attacks nor models import
evaluation, and no dataset imports an attack. Relative imports are refused: the check reads
absolute module names.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from pcdet_atlas.config import REPO_ROOT

PACKAGE = REPO_ROOT / "pcdet_atlas"
BOTTOM = {"config", "config_values", "registry", "utils", "ops", "version"}
LAYERS = ["evaluation", "datasets", "attacks", "models", "train_utils"]
#: layer -> the layers (besides BOTTOM) it may import
ALLOWED = {
    **{name: set() for name in BOTTOM},
    "evaluation": set(),
    "datasets": {"evaluation"},
    "attacks": {"datasets"},
    "models": {"datasets"},
    "train_utils": {"evaluation", "datasets", "attacks", "models"},
}


def layer_of(module: str) -> str | None:
    """``pcdet_atlas.x.y`` -> ``x`` (``None`` for the package itself or another package)."""
    parts = module.split(".")
    return parts[1] if parts[0] == "pcdet_atlas" and len(parts) > 1 else None


def imports_of(path: Path) -> list[tuple[str, int]]:
    """Every ``pcdet_atlas`` module a file imports (function-level imports included)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level > 0:
            found.append(("<relative>", node.lineno))  # the layer check needs absolute names
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.append((node.module, node.lineno))
            if node.module == "pcdet_atlas":  # from pcdet_atlas import attacks
                found += [(f"pcdet_atlas.{alias.name}", node.lineno) for alias in node.names]
    return found


def upward_imports(package: Path = PACKAGE) -> list[str]:
    bad = []
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(package)
        own = rel.parts[0].removesuffix(".py") if rel.parts[0] != "__init__.py" else None
        if own is None:
            continue  # the package's __init__ may expose anything
        assert own in ALLOWED, f"{rel}: layer {own!r} is not in the layer table of this test"
        for module, line in imports_of(path):
            if module == "<relative>":
                bad.append(f"pcdet_atlas/{rel}:{line} ({own}) uses a relative import")
                continue
            target = layer_of(module)
            if target is None or target == own or target in BOTTOM and own in BOTTOM:
                continue
            if target not in BOTTOM and target not in ALLOWED[own]:
                bad.append(f"pcdet_atlas/{rel}:{line} ({own}) imports {module} ({target})")
    return bad


def test_no_package_imports_a_layer_above_it():
    assert upward_imports() == []


@pytest.mark.parametrize(
    "layer,source,culprit",
    [
        (
            "models",
            "from pcdet_atlas.evaluation.waymo_metric import waymo_evaluate\n",
            "evaluation",
        ),
        ("datasets", "def f():\n    from pcdet_atlas.attacks import raycast\n", "attacks"),
        ("ops", "import pcdet_atlas.datasets.waymo_format\n", "datasets"),
        ("evaluation", "from pcdet_atlas import models\n", "models"),
        ("models", "from ..evaluation import waymo_metric\n", "relative import"),
    ],
)
def test_the_check_finds_an_upward_import(tmp_path, layer, source, culprit):
    (tmp_path / layer).mkdir()
    (tmp_path / layer / "bad.py").write_text(source)
    (tmp_path / "utils.py").write_text("from pcdet_atlas.ops import boxes\n")  # allowed
    found = upward_imports(tmp_path)
    assert len(found) == 1 and culprit in found[0] and "bad.py" in found[0], found

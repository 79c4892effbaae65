"""The package's layers import only downward (checked on the source with ``ast``, no importing).

bottom (config, config_values, registry, utils, ops, version) <- evaluation <- datasets
<- attacks, models <- train_utils <- integrations (bridges to other toolkits, which only tools
and users import). Datasets may call the Waymo metric (OpenPCDet's
``dataset.evaluation``); models read dataset configs; neither attacks nor models import
evaluation, and no dataset imports an attack. Relative imports are refused: the check reads
absolute module names. No module imports another of the package inside a function (the way to
dodge an import cycle) unless :data:`DEFERRED_IMPORTS` lists it with the reason.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from pcdet_atlas.config import REPO_ROOT

PACKAGE = REPO_ROOT / "pcdet_atlas"
BOTTOM = {"config", "config_values", "registry", "utils", "ops", "version"}
LAYERS = ["evaluation", "datasets", "attacks", "models", "train_utils", "integrations"]
#: layer -> the layers (besides BOTTOM) it may import
ALLOWED = {
    **{name: set() for name in BOTTOM},
    "evaluation": set(),
    "datasets": {"evaluation"},
    "attacks": {"datasets"},
    "models": {"datasets"},
    "train_utils": {"evaluation", "datasets", "attacks", "models"},
    "integrations": {"evaluation", "datasets", "attacks", "models", "train_utils"},
}


#: (file under pcdet_atlas/, module) -> why that module is imported inside a function there; a
#: cycle is never a reason (move the shared part into a module of its own instead)
DEFERRED_IMPORTS = {
    ("datasets/waymo_dataset.py", "pcdet_atlas.evaluation.waymo_metric"): (
        "scipy and jsonschema load only when a split is scored, not in every dataset user"
    ),
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
        ("train_utils", "from pcdet_atlas.integrations import openpcdet\n", "integrations"),
    ],
)
def test_the_check_finds_an_upward_import(tmp_path, layer, source, culprit):
    (tmp_path / layer).mkdir()
    (tmp_path / layer / "bad.py").write_text(source)
    (tmp_path / "utils.py").write_text("from pcdet_atlas.ops import boxes\n")  # allowed
    found = upward_imports(tmp_path)
    assert len(found) == 1 and culprit in found[0] and "bad.py" in found[0], found


def function_level_imports(package: Path = PACKAGE) -> list[tuple[str, str, int]]:
    """``(file, module, line)`` of every ``pcdet_atlas`` module imported inside a function."""
    found = []
    for path in sorted(package.rglob("*.py")):
        rel = str(path.relative_to(package))
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for inner in ast.walk(node):
                names = []
                if isinstance(inner, ast.Import):
                    names = [alias.name for alias in inner.names]
                elif isinstance(inner, ast.ImportFrom) and (inner.module or "").startswith(
                    "pcdet_atlas"
                ):
                    names = [inner.module]
                found += [(rel, n, inner.lineno) for n in names if n.startswith("pcdet_atlas")]
    return sorted(set(found))


def test_no_function_level_import_of_the_package():
    found = function_level_imports()
    unexplained = [f"pcdet_atlas/{f}:{line} imports {m}" for f, m, line in found
                   if (f, m) not in DEFERRED_IMPORTS]  # fmt: skip
    assert unexplained == [], "import at the top of the module (a cycle: split the module)"
    stale = set(DEFERRED_IMPORTS) - {(f, m) for f, m, _ in found}
    assert not stale, f"DEFERRED_IMPORTS lists imports that are gone: {sorted(stale)}"


def test_the_check_finds_a_function_level_import(tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "head.py").write_text(
        "import math\n\n\ndef names():\n    from pcdet_atlas.models import convert\n"
        "    import json\n"
    )
    assert function_level_imports(tmp_path) == [("models/head.py", "pcdet_atlas.models", 5)]

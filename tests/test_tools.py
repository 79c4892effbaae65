"""No tool imports another tool: what two tools share lives in the package, where a test or a
third tool can call it (checked on the source with ``ast``, no importing). Running another tool
as a child process (``tools/reproduce.py`` starts ``tools/test.py`` per model) is not an import.
``tools/official_waymo_metric/`` is left out: a project of its own, run in its own TensorFlow venv
without this package (its fixture script reads its evaluation script's helpers).
"""

from __future__ import annotations

import ast
from pathlib import Path

from pcdet_atlas.config import REPO_ROOT

TOOLS = REPO_ROOT / "tools"
OWN_PROJECTS = ("official_waymo_metric",)
#: calls that load a file as a module
LOADERS = {"load_tool", "spec_from_file_location", "run_path", "import_module", "__import__"}


def tool_imports(tools: Path = TOOLS) -> list[str]:
    """``<tool>:<line> <what>`` for every import of a tool module and every call that loads a
    file or module by name in ``tools/**/*.py``."""
    paths = [p for p in sorted(tools.rglob("*.py"))
             if p.relative_to(tools).parts[0] not in OWN_PROJECTS]  # fmt: skip
    names = {path.stem for path in paths}
    found = []
    for path in paths:
        rel = path.relative_to(tools.parent)
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            modules = []
            if isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                modules = [node.module or "." * node.level]
                if node.level:
                    modules = ["<relative import>"]
            for module in modules:
                top = module.split(".")[0]
                if top == "tools" or top in names or module == "<relative import>":
                    found.append(f"{rel}:{node.lineno} imports {module}")
            if isinstance(node, ast.Call):
                func = node.func
                name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
                if name in LOADERS:
                    found.append(f"{rel}:{node.lineno} calls {name}")
    return found


def test_no_tool_imports_another_tool():
    assert tool_imports() == []


def test_the_check_finds_a_tool_importing_a_tool(tmp_path):
    tools = tmp_path / "tools"
    tools.mkdir()
    (tools / "test.py").write_text("import argparse\n\nfrom pcdet_atlas import models\n")
    (tools / "reproduce.py").write_text(
        "from pcdet_atlas.utils.common import load_tool\n\n"
        "import test\n\n\ndef main():\n    return load_tool('test').main([])\n"
    )
    (tools / "report.py").write_text("from tools.test import main\nimport importlib.util\n")
    assert tool_imports(tools) == [
        "tools/report.py:1 imports tools.test",
        "tools/reproduce.py:3 imports test",
        "tools/reproduce.py:7 calls load_tool",
    ]

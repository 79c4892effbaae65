"""No tool imports another tool: what two tools share lives in the package, where a test or a
third tool can call it (checked on the source with ``ast``, no importing). Running another tool
as a child process (``tools/reproduce.py`` starts ``tools/test.py`` per model) is not an import.
``tools/dev/official_waymo_metric/`` is left out: a project of its own, run in its own
TensorFlow venv without this package (its fixture script reads its evaluation script's helpers).
"""

from __future__ import annotations

import argparse
import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest
from tool_parsers import read_parsers

from pcdet_atlas.config import REPO_ROOT

TOOLS = REPO_ROOT / "tools"
OWN_PROJECTS = ("official_waymo_metric",)
#: calls that load a file as a module
LOADERS = {"load_tool", "spec_from_file_location", "run_path", "import_module", "__import__"}


def tool_imports(tools: Path = TOOLS) -> list[str]:
    """``<tool>:<line> <what>`` for every import of a tool module and every call that loads a
    file or module by name in ``tools/**/*.py``."""
    paths = [p for p in sorted(tools.rglob("*.py"))
             if not set(p.relative_to(tools).parts) & set(OWN_PROJECTS)]  # fmt: skip
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


def test_tools_are_grouped_by_purpose():
    """The tools a user runs to benchmark sit at the top of tools/; data creation, benchmarks and
    developer tools in their subfolders, each listed in tools/README.md."""
    top = {p.stem for p in TOOLS.glob("*.py")}
    assert top == {
        "train", "test", "demo", "report", "reproduce", "evaluate_predictions", "openpcdet_test"
    }  # fmt: skip
    assert {p.name for p in TOOLS.iterdir() if p.is_dir() and p.name != "__pycache__"} == {
        "data", "bench", "dev"
    }  # fmt: skip
    readme = (TOOLS / "README.md").read_text()
    for path in TOOLS.rglob("*.py"):
        if not set(path.relative_to(TOOLS).parts) & set(OWN_PROJECTS):
            assert f"`{path.relative_to(TOOLS).as_posix()}`" in readme, path


def test_every_flag_is_snake_case_with_help_and_long_parsers_have_groups():
    """One flag style: ``--snake_case`` (an old spelling kept one release by ``RenamedFlag`` is
    listed after the new one), help on every flag, and argparse groups in a tool with more than
    12 flags."""
    tools = [str(p) for p in sorted(TOOLS.rglob("*.py"))
             if not set(p.relative_to(TOOLS).parts) & set(OWN_PROJECTS)
             and 'if __name__ == "__main__":' in p.read_text()]  # fmt: skip
    parsers = {tool: [row for row in rows if row[1] != argparse.SUPPRESS]
               for tool, rows in read_parsers(tools).items()}  # fmt: skip
    assert sorted(parsers) == tools, "a tool ran to the end without parsing its arguments"
    bad = []
    for tool, flags in parsers.items():
        name = Path(tool).relative_to(TOOLS)
        for options, help_text, _ in flags:
            if not help_text:
                bad.append(f"{name}: {options[0]} has no help")
            first = options[0] if options[0].startswith("--") else options[-1]
            if "-" in first[2:] or first.lower() != first and first not in ("-h",):
                bad.append(f"{name}: {first} is not --snake_case")
        groups = {group for _, _, group in flags} - {"options"}
        if len(flags) > 12 and not groups:
            bad.append(f"{name}: {len(flags)} flags and no argparse group")
    assert bad == [], "\n".join(bad)


def test_an_old_flag_spelling_still_works_and_warns(capsys):
    from pcdet_atlas.utils.cli import RenamedFlag

    parser = argparse.ArgumentParser(prog="tool")
    parser.add_argument("--out_dir", "--out", action=RenamedFlag, old=("--out",), required=True)
    assert parser.parse_args(["--out_dir", "a"]).out_dir == "a"
    assert capsys.readouterr().err == ""
    assert parser.parse_args(["--out", "b"]).out_dir == "b"
    assert capsys.readouterr().err.strip() == (
        "tool: warning: --out is deprecated and goes in the next release; use --out_dir"
    )
    with pytest.raises(ValueError, match="--old"):
        parser.add_argument("--new", action=RenamedFlag, old=("--old",))


def test_every_tool_ends_user_errors_in_one_line():
    """Each tool runs its ``main`` through ``run_tool`` and lists ``--debug`` in its help."""
    missing = []
    for path in sorted(TOOLS.rglob("*.py")):
        if set(path.relative_to(TOOLS).parts) & set(OWN_PROJECTS):
            continue
        text = path.read_text()
        if 'if __name__ == "__main__":' not in text:
            continue
        if "run_tool(main)" not in text or "add_debug_flag(" not in text:
            missing.append(path.name)
    assert missing == [], "tools without run_tool(main) / add_debug_flag(parser)"


def test_a_user_error_is_one_line_and_exit_2_and_debug_shows_the_traceback():
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, str(TOOLS / "report.py"), "--results", "/nonexistent/results"]
    cmd.append("--out_dir")
    cmd.append(str(Path("/nonexistent/report")))
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 2, run.stderr[-2000:]
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("report.py: error: "), run.stderr[-2000:]
    assert "/nonexistent/results" in lines[0] and "--debug" in lines[0]
    run = subprocess.run([*cmd, "--debug"], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 1 and "Traceback" in run.stderr, run.stderr[-2000:]
    helped = subprocess.run([*cmd[:2], "--help"], capture_output=True, text=True, env=env)
    assert "--debug" in helped.stdout


def test_a_tools_own_exit_message_is_a_user_error(monkeypatch, capsys):
    """``raise SystemExit("...")`` in a tool (a missing dataset, a refused stage) ends as every
    user error does: one line naming the tool, exit status 2 (Python's default for a message is
    1); an exit status passes through."""
    from pcdet_atlas.utils.cli import run_tool

    monkeypatch.setattr(sys, "argv", [str(TOOLS / "test.py")])

    def stops(code):
        def main():
            raise SystemExit(code)

        return main

    with pytest.raises(SystemExit) as done:
        run_tool(stops("cfgs/x.yaml: DATA_CONFIG.DATA_PATH 'data/x' does not exist"), argv=[])
    assert done.value.code == 2
    assert capsys.readouterr().err == (
        "test.py: error: cfgs/x.yaml: DATA_CONFIG.DATA_PATH 'data/x' does not exist\n"
    )
    for code in (0, 3, None):
        with pytest.raises(SystemExit) as done:
            run_tool(stops(code), argv=[])
        assert done.value.code == code


def test_a_bug_keeps_its_traceback():
    from pcdet_atlas.utils.cli import is_user_error, run_tool

    def buggy():
        raise IndexError("a bug")

    with pytest.raises(IndexError):
        run_tool(buggy, argv=[])
    assert not is_user_error(IndexError("x")) and is_user_error(FileNotFoundError("x"))
    from pcdet_atlas.config import ConfigError
    from pcdet_atlas.registry import RegistryError

    assert is_user_error(ConfigError("x")) and is_user_error(RegistryError("x"))


def test_a_tool_refuses_the_package_of_another_tree(tmp_path):
    from pcdet_atlas.utils.cli import OtherTreeError, check_package_tree

    check_package_tree(TOOLS / "test.py")  # this checkout's tool and package
    other = tmp_path / "clone"
    (other / "tools").mkdir(parents=True)
    (other / "pcdet_atlas").mkdir()
    with pytest.raises(OtherTreeError, match=r"test\.py of .*clone imports pcdet_atlas from"):
        check_package_tree(other / "tools" / "test.py")
    with pytest.raises(OtherTreeError, match=r"bench_models\.py of .*clone imports"):
        check_package_tree(other / "tools" / "bench" / "bench_models.py")  # a tool in a subfolder
    check_package_tree(TOOLS / "bench" / "bench_models.py")
    check_package_tree(tmp_path / "scripts" / "mine.py")  # a script outside any checkout


def test_a_benchmark_baseline_child_may_import_the_named_tree(tmp_path, monkeypatch):
    """--baseline_src runs this checkout's benchmark with another tree's package on purpose: the
    child names that tree (baseline_tree_env), and only that tree is accepted."""
    from pcdet_atlas.utils import cli

    repo = Path(cli.__file__).resolve().parents[2]
    other = tmp_path / "clone"
    (other / "tools" / "bench").mkdir(parents=True)
    (other / "pcdet_atlas").mkdir()
    env = cli.baseline_tree_env(repo)
    assert env[cli.BASELINE_TREE_ENV] == str(repo)
    assert env["PYTHONPATH"].split(os.pathsep)[0] == str(repo)
    monkeypatch.setenv(cli.BASELINE_TREE_ENV, str(repo))
    cli.check_package_tree(other / "tools" / "bench" / "bench_models.py")
    monkeypatch.setenv(cli.BASELINE_TREE_ENV, str(tmp_path / "elsewhere"))
    with pytest.raises(cli.OtherTreeError):
        cli.check_package_tree(other / "tools" / "bench" / "bench_models.py")

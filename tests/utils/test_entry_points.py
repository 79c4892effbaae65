"""The console commands of pyproject.toml run the tools of this checkout."""

import re

import pytest
import tomllib

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.utils import entry_points
from pcdet_atlas.utils.entry_points import COMMANDS, run_command


def test_pyproject_declares_each_command_and_each_runs_an_existing_tool():
    project = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]
    scripts = project["scripts"]
    assert set(scripts) == set(COMMANDS)
    for command, target in scripts.items():
        module, function = target.split(":")
        assert module == "pcdet_atlas.utils.entry_points" and callable(
            getattr(entry_points, function)
        )
        assert (REPO_ROOT / COMMANDS[command]).is_file(), command
    assert project["dynamic"] == ["version"] and "torch>=2.5" in project["dependencies"]


def test_a_command_runs_its_tool_with_the_given_flags(capsys, monkeypatch):
    monkeypatch.setattr("sys.argv", ["atlas-report"])  # restored after the test
    with pytest.raises(SystemExit) as done:
        run_command("atlas-report", ["--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith("usage: report.py")


def test_without_the_tools_folder_the_command_says_what_is_missing(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(entry_points, "REPO_ROOT", tmp_path)
    with pytest.raises(SystemExit) as done:
        run_command("atlas-test", [])
    assert done.value.code == 2  # a user error, as the tools exit
    assert re.search(r"atlas-test: error: .*tools/test.py is missing", capsys.readouterr().err)

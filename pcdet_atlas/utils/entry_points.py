"""Console commands (``atlas-train``, ``atlas-test``, ...; ``[project.scripts]`` in
pyproject.toml) for a source checkout installed with ``pip install -e .``.

Each runs the tool of the same purpose from ``tools/`` of the checkout the package is imported
from, as ``python tools/<tool>.py`` would: the same flags, output and exit status. The tools stay
scripts (their paths are what the docs show); a command here only finds the right one.
"""

from __future__ import annotations

import runpy
import sys

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.utils.cli import USER_ERROR_EXIT

__all__ = ["COMMANDS", "demo", "evaluate_predictions", "report", "reproduce", "test", "train"]

#: console command -> the tool it runs, relative to the checkout
COMMANDS = {
    "atlas-train": "tools/train.py",
    "atlas-test": "tools/test.py",
    "atlas-report": "tools/report.py",
    "atlas-reproduce": "tools/reproduce.py",
    "atlas-demo": "tools/demo.py",
    "atlas-evaluate-predictions": "tools/evaluate_predictions.py",
}


def run_command(command: str, argv: list[str] | None = None) -> None:
    """Run ``command``'s tool as ``__main__`` with ``argv`` (default: this process's arguments).

    Raises:
        SystemExit: status 2 naming the missing file, when the package is not a source checkout
            with its ``tools/`` (a non-editable install).
    """
    tool = REPO_ROOT / COMMANDS[command]
    if not tool.is_file():
        print(
            f"{command}: error: {tool} is missing; the console commands run the tools of a source "
            "checkout: clone the repository and `pip install -e .` in it",
            file=sys.stderr,
        )
        sys.exit(USER_ERROR_EXIT)
    sys.argv = [str(tool), *(sys.argv[1:] if argv is None else argv)]
    runpy.run_path(str(tool), run_name="__main__")


def train() -> None:
    run_command("atlas-train")


def test() -> None:
    run_command("atlas-test")


def report() -> None:
    run_command("atlas-report")


def reproduce() -> None:
    run_command("atlas-reproduce")


def demo() -> None:
    run_command("atlas-demo")


def evaluate_predictions() -> None:
    run_command("atlas-evaluate-predictions")

"""Every tool's argument parser, read without running the tool: each runs as ``__main__`` in one
child process until it parses its arguments, which stops it (tests/test_docs.py checks the
documented flags against them, tests/test_tools.py their style)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from pcdet_atlas.config import REPO_ROOT

SCRIPT = r"""
import argparse, json, runpy, sys

class Parsed(Exception):
    pass

def capture(self, *args, **kwargs):
    raise Parsed(self)

argparse.ArgumentParser.parse_args = capture
argparse.ArgumentParser.parse_known_args = capture
found = {}
for path in sys.argv[1:]:
    sys.argv = [path]
    try:
        runpy.run_path(path, run_name="__main__")
    except Parsed as parsed:
        found[path] = [
            [action.option_strings, action.help, group.title]
            for group in parsed.args[0]._action_groups for action in group._group_actions
            if action.option_strings
        ]
print(json.dumps(found))
"""


def read_parsers(tools: list[str]) -> dict[str, list[tuple[list[str], str | None, str]]]:
    """``{tool: [(option strings, help, argparse group title), ...]}`` for each tool path
    (relative to the repository root or absolute) that parses its arguments; a tool that runs to
    the end without parsing is missing from the result."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run([sys.executable, "-c", SCRIPT, *tools], cwd=REPO_ROOT, env=env,
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])

"""Which source tree produced a result: the git commit of the checkout the package is imported
from, and whether its tracked files differed from that commit.

``results.json`` records both (``source_commit``, ``source_dirty``) beside the package version,
so a number in a report can be traced to the code that computed it. Outside a git checkout (an
installed wheel, a source archive) or without a ``git`` executable, both are None: unknown, never
guessed.
"""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

from pcdet_atlas.config import REPO_ROOT

__all__ = ["SourceRevision", "source_revision"]


@dataclass(frozen=True)
class SourceRevision:
    """``commit``: the 40-hex-digit HEAD commit; ``dirty``: True when a tracked file differs
    from it (untracked files do not count)."""

    commit: str
    dirty: bool


def _git(root: Path, *args: str) -> str | None:
    git = shutil.which("git")
    if git is None:
        return None
    try:
        done = subprocess.run(
            [git, "-C", str(root), *args],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout if done.returncode == 0 else None


def source_revision(root: str | Path = REPO_ROOT) -> SourceRevision | None:
    """The git revision of the checkout at ``root`` (default: the tree this package lives in),
    or None when ``root`` is not the top of a git work tree or git cannot tell."""
    root = Path(root).resolve()
    top = _git(root, "rev-parse", "--show-toplevel")
    if top is None or Path(top.strip()).resolve() != root:
        return None  # not a checkout of this project (e.g. installed inside another repo)
    commit = _git(root, "rev-parse", "--verify", "HEAD")
    status = _git(root, "status", "--porcelain", "--untracked-files=no")
    if commit is None or status is None:
        return None
    return SourceRevision(commit=commit.strip(), dirty=bool(status.strip()))

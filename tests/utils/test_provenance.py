"""source_revision: the commit and dirty state of a checkout, None where git cannot tell."""

import shutil
import subprocess

import pytest

from pcdet_atlas.utils.provenance import SourceRevision, source_revision

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs a git executable")


def _git(root, *args):
    return subprocess.run(
        ["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t", *args],
        check=True, capture_output=True, text=True,
    ).stdout.strip()  # fmt: skip


def test_a_checkouts_commit_and_whether_tracked_files_changed(tmp_path):
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.txt").write_text("one\n")
    _git(tmp_path, "add", "a.txt")
    _git(tmp_path, "commit", "-q", "-m", "first")
    head = _git(tmp_path, "rev-parse", "HEAD")
    assert source_revision(tmp_path) == SourceRevision(commit=head, dirty=False)
    (tmp_path / "untracked.txt").write_text("x\n")  # untracked files do not count
    assert source_revision(tmp_path).dirty is False
    (tmp_path / "a.txt").write_text("two\n")
    assert source_revision(tmp_path) == SourceRevision(commit=head, dirty=True)
    (tmp_path / "sub").mkdir()  # inside a checkout, but not its top: not this project's tree
    assert source_revision(tmp_path / "sub") is None


def test_no_checkout_no_commit_and_an_empty_repository_none(tmp_path):
    assert source_revision(tmp_path) is None
    _git(tmp_path, "init", "-q")  # no commit yet: HEAD does not resolve
    assert source_revision(tmp_path) is None

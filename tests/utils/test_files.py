"""Writes at fixed names in a folder that may hold planted symlinks: pcdet_atlas.utils.files."""

import os
import stat

import pytest

from pcdet_atlas.utils import common
from pcdet_atlas.utils.files import NotARegularFileError, open_regular_file, write_atomic

VICTIM_TEXT = "IMPORTANT USER DATA\n"


@pytest.fixture
def victim(tmp_path):
    """A file outside the folder the code is given, which a planted symlink points at."""
    path = tmp_path / "outside" / "victim.txt"
    path.parent.mkdir()
    path.write_text(VICTIM_TEXT)
    return path


def test_write_atomic_replaces_a_symlink_instead_of_writing_through_it(tmp_path, victim):
    folder = tmp_path / "received"
    folder.mkdir()
    (folder / "report.md").symlink_to(victim)
    write_atomic(folder / "report.md", lambda f: f.write(b"new"))
    assert victim.read_text() == VICTIM_TEXT
    assert not (folder / "report.md").is_symlink() and (folder / "report.md").read_bytes() == b"new"
    assert sorted(p.name for p in folder.iterdir()) == ["report.md"]  # no temporary file left
    assert common.write_atomic is write_atomic  # its old home serves the same function


@pytest.mark.parametrize("flags", [os.O_RDWR, os.O_WRONLY | os.O_APPEND, os.O_WRONLY | os.O_TRUNC])
def test_open_regular_file_refuses_a_symlink_naming_the_path(tmp_path, victim, flags):
    link = tmp_path / "x.log"
    link.symlink_to(victim)
    with pytest.raises(NotARegularFileError) as err:
        open_regular_file(link, flags, "the log of a test")
    assert str(err.value).startswith(f"{link}: a symlink to {victim}, expected the log of a test")
    assert victim.read_text() == VICTIM_TEXT
    dangling = tmp_path / "y.log"  # a link to a file not there yet is not created through either
    dangling.symlink_to(tmp_path / "outside" / "created.txt")
    with pytest.raises(NotARegularFileError, match="a symlink to"):
        open_regular_file(dangling, flags, "the log of a test")
    assert not (tmp_path / "outside" / "created.txt").exists()


def test_open_regular_file_refuses_a_fifo_or_a_folder_without_waiting(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for flags in (os.O_WRONLY, os.O_RDWR):  # O_WRONLY without a reader would block
        with pytest.raises(NotARegularFileError, match=r"fifo: not a regular file \(p"):
            open_regular_file(fifo, flags, "a lock file")
    (tmp_path / "dir").mkdir()
    with pytest.raises(NotARegularFileError, match=r"dir: not a regular file \(d"):
        open_regular_file(tmp_path / "dir", os.O_RDWR, "a lock file")


def test_open_regular_file_creates_appends_and_truncates_a_regular_file(tmp_path):
    path = tmp_path / "a.log"
    fd = open_regular_file(path, os.O_WRONLY | os.O_APPEND, "a log")
    os.write(fd, b"one\n")
    os.close(fd)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~_umask()
    fd = open_regular_file(path, os.O_WRONLY | os.O_APPEND, "a log")
    assert os.get_blocking(fd)  # O_NONBLOCK only while opening
    os.write(fd, b"two\n")
    os.close(fd)
    assert path.read_text() == "one\ntwo\n"
    fd = open_regular_file(path, os.O_WRONLY | os.O_TRUNC, "a log")
    os.close(fd)
    assert path.read_text() == ""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask

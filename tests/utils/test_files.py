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


def test_a_log_file_is_appended_to_and_a_planted_link_refused(tmp_path):
    """The tools' log files (``train_*.log``, ``log_eval_*.txt``) go through the same check as
    the other files they write: a symlink at the log's name is refused, its target untouched."""
    import logging

    from pcdet_atlas.utils.common import create_logger

    log = tmp_path / "run" / "train.log"
    logger = create_logger(log, name="atlas-test-log")
    logger.info("first")
    logger = create_logger(log, name="atlas-test-log")  # a second call appends, closes the first
    logger.info("second")
    logging.getLogger("atlas-test-log").handlers[-1].flush()
    assert [line.split()[-1] for line in log.read_text().splitlines()] == ["first", "second"]
    victim = tmp_path / "victim.txt"
    victim.write_text("IMPORTANT\n")
    planted = tmp_path / "run" / "planted.log"
    planted.symlink_to(victim)
    with pytest.raises(NotARegularFileError, match=r"planted\.log: a symlink to .*victim\.txt"):
        create_logger(planted, name="atlas-test-log")
    assert victim.read_text() == "IMPORTANT\n"

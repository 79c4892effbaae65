"""One writer per output folder: pcdet_atlas.utils.locks and the tools' use of it."""

import contextlib
import os
import signal
import socket
import subprocess
import sys

import pytest

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.train_utils.setup import lock_output_folder
from pcdet_atlas.utils.cli import run_tool
from pcdet_atlas.utils.files import NotARegularFileError
from pcdet_atlas.utils.locks import FolderLock, FolderLockedError, lock_path

HOLD = """
import sys, time
from pcdet_atlas.utils.locks import FolderLock
FolderLock(sys.argv[1], "a test holder").acquire()
print("locked", flush=True)
time.sleep(60)
"""


def test_a_second_lock_fails_naming_the_holder_and_succeeds_after_release(tmp_path):
    folder = tmp_path / "run"
    first = FolderLock(folder, "training").acquire()
    assert lock_path(folder) == tmp_path / ".run.lock" and first.held
    with pytest.raises(FolderLockedError) as err:
        FolderLock(folder, "evaluation").acquire()
    message = str(err.value)
    assert "\n" not in message and str(folder) in message
    assert f"training by PID {os.getpid()} on {socket.gethostname()}, started 20" in message
    first.release()
    assert not lock_path(folder).exists()  # a released lock leaves no file
    first.release()  # releasing twice does nothing
    with FolderLock(folder / ".." / "run", "evaluation") as again:  # another name, one lock
        assert again.held
    assert not again.held and not lock_path(folder).exists()


def test_the_lock_of_a_killed_process_is_free(tmp_path):
    folder = tmp_path / "run"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline() == "locked\n"
        with pytest.raises(FolderLockedError, match=f"a test holder by PID {holder.pid} on "):
            FolderLock(folder, "evaluation").acquire()
    finally:
        holder.kill()  # SIGKILL: no release, the lock file and its record stay
        holder.wait()
    assert str(holder.pid) in lock_path(folder).read_text()
    with FolderLock(folder, "evaluation"):
        assert '"purpose": "evaluation"' in lock_path(folder).read_text()


def test_a_tool_stops_with_one_line_naming_the_holder(tmp_path, capsys):
    folder = tmp_path / "run"
    with FolderLock(folder, "training"), contextlib.ExitStack() as held:
        with pytest.raises(SystemExit) as exc:
            lock_output_folder(folder, held, "tools/test.py")
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {folder} is in use: training by PID")


def test_a_killed_holder_that_never_recorded_itself_is_named_as_such(tmp_path):
    """A lock file without a record (its holder killed before writing it) still locks while held
    and is free once that process ends."""
    folder = tmp_path / "run"
    path = lock_path(folder)
    path.write_text("")
    script = (
        "import fcntl, os, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDWR)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "print('locked', flush=True)\n"
        "time.sleep(60)\n"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", script, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline() == "locked\n"
        with pytest.raises(FolderLockedError, match="has not recorded itself yet"):
            FolderLock(folder, "training").acquire()
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    with FolderLock(folder, "training"):
        pass


def test_a_symlink_planted_at_the_lock_path_is_refused_not_followed(tmp_path, capsys, monkeypatch):
    """A received output folder with ``.<name>.lock -> ~/.bashrc`` beside it: the lock is not
    taken through the link (which would truncate the target and write the record into it)."""
    victim = tmp_path / "victim"
    victim.write_text("IMPORTANT USER DATA\n")
    folder = tmp_path / "output" / "run"
    folder.parent.mkdir()
    lock_path(folder).symlink_to(victim)
    with pytest.raises(NotARegularFileError) as err:
        FolderLock(folder, "training").acquire()
    assert str(err.value).startswith(f"{lock_path(folder)}: a symlink to {victim}, expected the "
                                     f"lock file of {folder} as a regular file")  # fmt: skip
    assert victim.read_text() == "IMPORTANT USER DATA\n" and lock_path(folder).is_symlink()
    monkeypatch.setattr(sys, "argv", [str(REPO_ROOT / "tools" / "train.py")])
    with pytest.raises(SystemExit) as exc:  # a tool: one line naming the path, exit 2
        run_tool(lambda: lock_output_folder(folder, contextlib.ExitStack(), "training"), argv=[])
    assert exc.value.code == 2
    err_line = capsys.readouterr().err
    assert err_line.count("\n") == 1 and f"{lock_path(folder)}: a symlink to {victim}" in err_line
    assert victim.read_text() == "IMPORTANT USER DATA\n"


def test_a_lock_path_that_is_not_a_regular_file_is_refused(tmp_path):
    folder = tmp_path / "run"
    os.mkfifo(lock_path(folder))  # opening a FIFO could hang, and it holds no record
    with pytest.raises(NotARegularFileError, match=r"\.run\.lock: not a regular file \(p"):
        FolderLock(folder, "training").acquire()

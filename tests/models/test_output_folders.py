"""The tools' output folders: a flag or a variant file cannot name a folder outside
--out_dir, and a second run into a folder another run writes stops at once, naming it."""

import os
import socket

import pytest
import torch

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.utils.common import load_tool
from pcdet_atlas.utils.locks import FolderLock
from pcdet_atlas.utils.paths import UnsafePathError

CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"
RUN = ("atlas", "synthetic", "centerpoint")


def args_of(tool, out, data, *flags):
    extra = ["--epochs", "1", "--default_malloc"] if tool == "train" else []
    return [
        "--cfg", str(CFG), "--out_dir", str(out), "--workers", "0", "--no_progress",
        "--device", "cpu", *extra, *flags, "--set", "DATA_CONFIG.DATA_PATH", str(data),
    ]  # fmt: skip


@pytest.mark.parametrize(
    "tool, flag, value",
    [("train", "--extra_tag", "../../.."), ("test", "--extra_tag", ".."),
     ("test", "--eval_tag", "../x"), ("test", "--eval_tag", "a/b")],
)  # fmt: skip
def test_a_tag_that_is_not_one_folder_name_is_a_usage_error(tool, flag, value, tmp_path, capsys):
    out = tmp_path / "a" / "b" / "c"
    with pytest.raises(SystemExit) as exc:
        load_tool(tool).main(args_of(tool, out, tmp_path, flag, value))
    assert exc.value.code == 2
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.endswith(f"error: argument {flag}: {value!r} is not one file or folder name of "
                        "letters, digits, '.', '_' and '-' that starts with a letter or digit "
                        "(no '/', not '.' or '..')")  # fmt: skip
    assert list(tmp_path.rglob("*")) == []


def test_a_variant_file_named_dot_dot_writes_nothing(tmp_path):
    variant = tmp_path / "...yaml"  # passed the VARIANT == file name check as variant '..'
    variant.write_text("NAME: CleanAttack\nVARIANT: '..'\n")
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    args = args_of("test", out, data, "--attacks", f"clean,{variant}")
    with pytest.raises(UnsafePathError, match=r"attack variant \(its file name\) '\.\.'"):
        load_tool("test").main(args)
    assert not out.exists()


def test_train_refuses_a_folder_another_run_writes(tmp_path, capsys):
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()  # the lock comes before the data is read
    folder = out.joinpath(*RUN, "held")
    with FolderLock(folder, "tools/train.py training"):
        with pytest.raises(SystemExit) as exc:
            load_tool("train").main(args_of("train", out, data, "--extra_tag", "held"))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    holder = f"tools/train.py training by PID {os.getpid()} on {socket.gethostname()}, started 20"
    assert f"error: {folder} is in use: {holder}" in err
    assert not folder.exists()  # no log, no config written


def test_test_refuses_an_evaluation_folder_another_run_writes(synthetic_root, tmp_path, capsys):
    torch.manual_seed(0)
    ckpt = tmp_path / "random.pth"
    torch.save({"model_state": build_network_from_config(cfg_from_yaml_file(CFG)).state_dict()},
               ckpt)  # fmt: skip
    out = tmp_path / "out"
    folder = out.joinpath(*RUN, "default", "eval", "random", "val", "default")
    args = args_of("test", out, synthetic_root, "--ckpt", str(ckpt))
    with FolderLock(folder, "tools/test.py evaluating random.pth"):
        with pytest.raises(SystemExit) as exc:
            load_tool("test").main(args)
    assert exc.value.code == 2
    assert f"error: {folder} is in use: tools/test.py evaluating" in capsys.readouterr().err
    assert not folder.exists()


def test_reproduce_refuses_an_out_folder_another_run_writes(tmp_path, capsys):
    out = tmp_path / "report"
    with FolderLock(out, "tools/reproduce.py"):
        with pytest.raises(SystemExit) as exc:
            load_tool("reproduce").main(["--out", str(out), "--report_only"])
    assert exc.value.code == 2
    assert f"error: {out} is in use: tools/reproduce.py by PID" in capsys.readouterr().err

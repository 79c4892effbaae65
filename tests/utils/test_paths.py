"""Names from data, configs and flags stay one path component inside their root."""

import os
import pickle
import re

import numpy as np
import pytest

from pcdet_atlas.attacks.base import build_attack
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.train_utils.atlas_eval import resolve_variants
from pcdet_atlas.train_utils.eval_utils import write_prediction_files
from pcdet_atlas.train_utils.setup import load_cfg, output_dir_for
from pcdet_atlas.utils.paths import (
    UnsafePathError,
    join_under,
    regular_file,
    relative_parts,
    resolve_under,
    safe_component,
)

UNSAFE = ["..", ".", "", "../../x", "a/b", "/etc", "a\\b", ".hidden", "-rf", "a b", "x\n", 3]


@pytest.mark.parametrize("value", ["default", "run1", "epoch_12", "inj_global-hard.v2", "a..b"])
def test_one_safe_name_passes(value):
    assert safe_component(value, "extra_tag", "--extra_tag") == value


@pytest.mark.parametrize("value", UNSAFE)
def test_anything_else_names_the_value_what_and_where(value):
    with pytest.raises(UnsafePathError) as err:
        safe_component(value, "frame_id", "x.pkl [frame 3]")
    assert f"frame_id {value!r} (from x.pkl [frame 3]) is not one file or folder name" in str(
        err.value
    )


def test_join_under_refuses_a_symlink_out_of_the_root(tmp_path):
    root, outside = tmp_path / "root", tmp_path / "outside"
    root.mkdir(), outside.mkdir()
    (root / "link").symlink_to(outside)
    assert join_under(root, ("a", "x"), ("b", "y"), source="s") == root / "a" / "b"
    with pytest.raises(
        UnsafePathError, match=r"link/b \(from s\) resolves to .*/outside/b, outside its root"
    ):
        join_under(root, ("link", "x"), ("b", "y"), source="s")
    with pytest.raises(UnsafePathError, match=r"y '\.\.' \(from s\)"):
        join_under(root, ("a", "x"), ("..", "y"), source="s")


def test_a_linked_checkpoint_or_evaluation_folder_is_refused(tmp_path):
    """A run folder's fixed subfolders (``ckpt/``, ``eval/``, ``tensorboard/``) are checked as
    the run folder is: one linked elsewhere would have had checkpoints pruned, or an evaluation
    emptied by ``--overwrite``, where it points."""
    from pcdet_atlas.train_utils.eval_folder import eval_dir

    cfg = load_cfg(str(REPO_ROOT / "cfgs/atlas/synthetic/cp4f.yaml"), [])
    out, elsewhere = tmp_path / "output", tmp_path / "elsewhere"
    run = output_dir_for(cfg, out, "default")
    assert output_dir_for(cfg, out, "default", ("ckpt", "folder")) == run / "ckpt"
    ckpt = tmp_path / "checkpoint_epoch_3.pth"
    assert eval_dir(cfg, str(out), "default", ckpt, "t") == run / "eval" / "epoch_3" / "val" / "t"
    run.mkdir(parents=True), elsewhere.mkdir()
    for sub in ("ckpt", "eval", "tensorboard"):
        (run / sub).symlink_to(elsewhere)
    for sub in ("ckpt", "tensorboard"):
        with pytest.raises(UnsafePathError, match=rf"{sub} \(from .*\) resolves to .*elsewhere"):
            output_dir_for(cfg, out, "default", (sub, "folder"))
    with pytest.raises(UnsafePathError, match=r"resolves to .*elsewhere/epoch_3/val/t, outside"):
        eval_dir(cfg, str(out), "default", ckpt, "t")


@pytest.mark.parametrize("value", ["a.bin", "db_1/seg-1_0001_Vehicle_0.bin", "a/b/c"])
def test_a_relative_path_of_safe_names_resolves_under_its_root(tmp_path, value):
    assert resolve_under(tmp_path, value, "path", "s") == tmp_path / value
    assert relative_parts(value, "path", "s") == tuple(value.split("/"))


@pytest.mark.parametrize(
    "value", ["/etc/passwd", "../x", "a/../../x", "a/..", "./a", "a//b", "a/", "", ".", "a/.b", 3]
)
def test_a_path_that_is_absolute_or_has_dot_parts_is_refused(tmp_path, value):
    with pytest.raises(UnsafePathError) as err:
        resolve_under(tmp_path, value, "path", "x.pkl Vehicle[3]")
    assert f"path {value!r} (from x.pkl Vehicle[3]) is not a relative path: names joined by '/'" \
        in str(err.value)  # fmt: skip


def test_resolve_under_refuses_a_symlink_out_of_the_root(tmp_path):
    root, outside = tmp_path / "root", tmp_path / "outside"
    root.mkdir(), outside.mkdir()
    (root / "db").symlink_to(outside)
    with pytest.raises(UnsafePathError, match=r"db/x\.bin \(from s\) resolves to .*/outside/x"):
        resolve_under(root, "db/x.bin", "path", "s")


def test_regular_file_refuses_fifos_devices_and_folders(tmp_path):
    (tmp_path / "f.bin").write_bytes(b"")
    os.mkfifo(tmp_path / "fifo")
    assert regular_file(tmp_path / "f.bin", "object") == tmp_path / "f.bin"
    for path, kind in [(tmp_path / "fifo", "a FIFO"), ("/dev/zero", "a character device"),
                       (tmp_path, "a folder")]:  # fmt: skip
        with pytest.raises(UnsafePathError, match=rf"object {path} is {kind}, not a regular file"):
            regular_file(path, "object")
    with pytest.raises(FileNotFoundError):
        regular_file(tmp_path / "missing", "object")


def test_save_to_file_refuses_a_frame_id_that_leaves_its_folder(tmp_path):
    out = tmp_path / "eval" / "clean" / "final_result" / "data"
    annos = [
        {"frame_id": fid, "name": np.array([]), "boxes_lidar": np.zeros((0, 7)),
         "score": np.array([])}
        for fid in ("seq_000", "../../x")
    ]  # fmt: skip
    with pytest.raises(UnsafePathError, match=r"frame_id '\.\./\.\./x' \(from prediction 1\)"):
        write_prediction_files(annos, out)
    assert list(tmp_path.rglob("*")) == []  # checked before anything is written
    write_prediction_files(annos[:1], out)
    assert [p.name for p in out.iterdir()] == ["seq_000.txt"]


def _sequence(root, name="segment-1_with_camera_labels", frames=1):
    infos = [
        wf.make_frame_info(name, i, np.eye(4), [10, 0, 0, 0, 0], 1000 * i) for i in range(frames)
    ]
    path = wf.sequence_pkl_path(root, name)
    path.parent.mkdir(parents=True)
    return path, infos


@pytest.mark.parametrize("key", ["frame_id", "lidar_sequence"])
def test_an_info_pkl_naming_a_path_outside_the_data_root_is_refused(tmp_path, key):
    path, infos = _sequence(tmp_path)
    if key == "frame_id":
        infos[0]["frame_id"] = "../../x"
    else:
        infos[0]["point_cloud"]["lidar_sequence"] = "../../x"
    path.write_bytes(pickle.dumps(infos))
    with pytest.raises(UnsafePathError, match=rf"'\.\./\.\./x' \(from {re.escape(str(path))} \["):
        wf.load_sequence_infos(path)


def test_a_split_file_or_caller_naming_a_sequence_outside_the_root_is_refused(tmp_path):
    split = tmp_path / "ImageSets" / "val.txt"
    split.parent.mkdir()
    split.write_text("segment-1_with_camera_labels.tfrecord\n\n../../etc/x.tfrecord\n")
    with pytest.raises(UnsafePathError, match=rf"'\.\./\.\./etc/x' \(from {re.escape(str(split))} "
                       r"line 3\)"):  # fmt: skip
        wf.read_image_set(split)
    for join in (wf.sequence_pkl_path, wf.sequence_dir):
        with pytest.raises(UnsafePathError, match=r"sequence name '\.\.'"):
            join(tmp_path, "..")
    with pytest.raises(UnsafePathError, match=r"sequence name '\.\./x'"):
        wf.frame_npy_path(tmp_path, "../x", 0)


def test_a_variant_named_dot_dot_is_refused(tmp_path):
    """``...yaml`` with ``VARIANT: '..'`` passed the name check (its stem is ``..``)."""
    variant = tmp_path / "...yaml"
    variant.write_text("NAME: CleanAttack\nVARIANT: '..'\n")
    with pytest.raises(UnsafePathError, match=rf"attack variant \(its file name\) '\.\.' "
                       rf"\(from --attacks: {re.escape(str(variant))}\)"):  # fmt: skip
        resolve_variants(f"clean,{variant}", {})
    cfg = cfg_from_yaml_file(variant)
    with pytest.raises(UnsafePathError, match=rf"VARIANT '\.\.' \(from {re.escape(str(variant))}"):
        build_attack(cfg)


def test_output_folders_refuse_unsafe_tags_and_config_names(tmp_path):
    base = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "centerpoint.yaml"
    cfg = load_cfg(str(base), None)
    out = tmp_path / "output"
    assert output_dir_for(cfg, out, "run1") == out / "atlas" / "synthetic" / "centerpoint" / "run1"
    with pytest.raises(UnsafePathError, match=r"extra_tag '\.\./\.\./\.\.' \(from the output"):
        output_dir_for(cfg, out, "../../..")
    dotted = tmp_path / "cfgs" / "...yaml"  # its stem, the config's TAG, is '..'
    dotted.parent.mkdir()
    dotted.write_text(f"_BASE_CONFIG_: {base}\n")
    with pytest.raises(UnsafePathError, match=r"config name '\.\.'"):
        output_dir_for(load_cfg(str(dotted), None), out, "default")
    assert not out.exists()

import json
import os
import re

import numpy as np
import pytest
from atlas_helpers import VEHICLES, load_tool, synthetic_library, write_tiny_waymo
from malicious_files import malicious_pickle

from pcdet_atlas.attacks.trace_library import TraceFilter, TraceLibrary, build_trace_library
from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.datasets.waymo_format import WaymoFormatError, read_image_set, sequence_pkl_path
from pcdet_atlas.utils.paths import UnsafePathError
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory):
    return write_tiny_waymo(tmp_path_factory.mktemp("tiny_lib"), frames={"train": 8, "val": 2})


def test_library_in_canonical_box_frame(tiny_root):
    lib = build_trace_library(tiny_root, TraceFilter(min_points=50, range_m=(0.0, 80.0)))
    sizes = {v[0]: np.array(v[5:8]) for v in VEHICLES}
    assert sorted(lib.obj_id.tolist()) == sorted(sizes)
    for k in range(len(lib)):
        tr = lib.trace(k)
        expected = sizes[tr.obj_id]
        np.testing.assert_allclose(tr.box_size, expected, rtol=1e-5)
        # every point inside the box, centred on it, heading along +x
        assert np.all(np.abs(tr.xyz) <= expected / 2 + 1e-3)
        assert np.abs(tr.xyz[:, 0]).max() > 0.45 * expected[0]  # the long axis is x
        assert (tr.src_range > 0).all() and np.isfinite(tr.intensity).all()
        assert lib.num_frames[k] == 8  # every train frame contributed
    assert lib.points.shape[0] == lib.offsets[-1]


def test_filters_range_band_min_points_and_cap(tiny_root):
    full = build_trace_library(tiny_root, TraceFilter(min_points=50, range_m=(0.0, 80.0)))
    near = build_trace_library(tiny_root, TraceFilter(min_points=50, range_m=(0.0, 15.0)))
    assert set(near.obj_id) < set(full.obj_id)  # far vehicles excluded by the band
    capped = build_trace_library(
        tiny_root, TraceFilter(min_points=50, range_m=(0.0, 80.0), max_points_per_trace=300)
    )
    assert capped.trace_sizes().max() == 300
    again = build_trace_library(
        tiny_root, TraceFilter(min_points=50, range_m=(0.0, 80.0), max_points_per_trace=300)
    )
    np.testing.assert_array_equal(capped.points, again.points)  # deterministic subsample
    with pytest.raises(ValueError, match="passes the trace filters"):
        build_trace_library(tiny_root, TraceFilter(min_points=10**6, max_points_per_trace=10**7))


def test_save_load_roundtrip_and_bad_file(tiny_root, tmp_path):
    lib = build_trace_library(tiny_root, TraceFilter(min_points=50))
    path = lib.save(tmp_path / "lib.npz")
    back = TraceLibrary.load(path)
    for name in ("points", "intensity", "elongation", "src_range", "offsets", "box_size"):
        np.testing.assert_array_equal(getattr(back, name), getattr(lib, name))
    assert back.build_info["filters"] == TraceFilter(min_points=50).to_dict()
    np.savez(tmp_path / "bad.npz", points=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="not a trace library"):
        TraceLibrary.load(tmp_path / "bad.npz")


def test_filter_config_keys():
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/attacks/inj_global_easy.yaml").TRACE_LIBRARY
    flt = TraceFilter.from_config(cfg)
    assert flt.classes == ("Vehicle",) and flt.range_m == (5.0, 50.0)
    cfg.MIN_PONTS = 3
    with pytest.raises(ConfigError, match="MIN_PONTS"):
        TraceFilter.from_config(cfg)


def test_build_tool_writes_under_data_root(tiny_root, capfd):
    out = load_tool("data/build_trace_library").main(
        ["--cfg", str(REPO_ROOT / "cfgs/attacks/inj_rel_easy.yaml"), "--data_path", str(tiny_root)]
    )
    assert out == tiny_root / "atlas_trace_library.npz"
    lib = TraceLibrary.load(out)
    assert len(lib) >= 1 and lib.build_info["split"] == "train"
    sizes = lib.trace_sizes()  # the summary line says min/median/max: it must print the median
    expected = f"{sizes.min()}/{int(np.median(sizes))}/{sizes.max()}"
    logged = capfd.readouterr()
    assert f"min/median/max {expected}" in logged.out + logged.err


def test_build_tool_reads_its_paths_from_the_working_directory(tiny_root, tmp_path, monkeypatch):
    """--data_path and --out as typed, relative to the working directory (not the repo root)."""
    monkeypatch.chdir(tiny_root.parent)
    args = ["--cfg", str(REPO_ROOT / "cfgs/attacks/inj_rel_easy.yaml"), "--data_path",
            tiny_root.name, "--out", os.path.relpath(tmp_path / "rel_lib.npz")]  # fmt: skip
    out = load_tool("data/build_trace_library").main(args)
    assert out == tmp_path / "rel_lib.npz" and out.is_file()
    assert TraceLibrary.load(out).build_info["split"] == "train"
    monkeypatch.chdir(tmp_path)  # the same relative --data_path names nothing here
    with pytest.raises(WaymoFormatError, match=str(tmp_path / tiny_root.name)):
        load_tool("data/build_trace_library").main(args)


def test_library_of_the_synthetic_dataset(synthetic_root, tmp_path):
    lib = TraceLibrary.load(synthetic_library(synthetic_root, tmp_path))
    assert len(lib) >= 5 and set(lib.sequence) <= set(
        read_image_set(synthetic_root / "ImageSets" / "train.txt")
    )
    for k in range(len(lib)):
        tr = lib.trace(k)
        assert len(tr) >= 200 and np.all(np.abs(tr.xyz) <= tr.box_size / 2 + 1e-3)
        assert (tr.src_range > 1.0).all() and (tr.src_range <= 60.0).all()  # band [5, 50] + box


def test_truncated_library_names_its_path(tiny_root, tmp_path):
    path = build_trace_library(tiny_root, TraceFilter(min_points=50)).save(tmp_path / "lib.npz")
    data = path.read_bytes()
    for size in (len(data) // 2, 10, 0):
        path.write_bytes(data[:size])
        with pytest.raises(ValueError, match=rf"{path}: cannot read the trace library"):
            TraceLibrary.load(path)


def _library_arrays():
    """The arrays of a one-trace library as :meth:`TraceLibrary.save` writes them."""
    return dict(
        points=np.zeros((2, 3), np.float32), intensity=np.zeros(2, np.float32),
        elongation=np.zeros(2, np.float32), src_range=np.full(2, 10.0, np.float32),
        offsets=np.array([0, 2]), box_size=np.array([[4.0, 2.0, 1.5]], np.float32),
        sequence=np.array(["seq"]), obj_id=np.array(["obj"]), num_frames=np.array([1]),
        build_info=np.array('{"split": "train"}'),
    )  # fmt: skip


@pytest.mark.parametrize(
    "edit, message",
    [
        ({"extra": np.zeros(1)}, r"not a trace library \(missing arrays \[\], unexpected arrays "
                                 r"\['extra'\]; expected exactly \['points', "),
        ({"build_info": np.array("{not json")}, r"build_info is not valid JSON \(Expecting"),
        ({"build_info": np.array("[1, 2]")}, r"build_info must be a JSON object, got list"),
        ({"points": np.array(["a", "b"])}, r"malformed trace library arrays: ValueError: could"),
    ],
)  # fmt: skip
def test_malformed_library_names_its_path(tmp_path, edit, message):
    """A loadable .npz with an extra array, bad build_info JSON or an array of the wrong type is
    a ValueError naming the library, not a bare TypeError/JSONDecodeError."""
    path = tmp_path / "lib.npz"
    arrays = _library_arrays()
    info = json.loads(str(arrays.pop("build_info")))
    assert TraceLibrary.load(TraceLibrary(**arrays, build_info=info).save(path)).build_info == info
    np.savez(path, **{**_library_arrays(), **edit})
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: {message}"):
        TraceLibrary.load(path)


def test_build_from_an_empty_split_names_the_split(tiny_root, tmp_path):
    import shutil

    root = tmp_path / "root"
    shutil.copytree(tiny_root, root)
    (root / "ImageSets" / "train.txt").write_text("\n")
    with pytest.raises(ValueError, match=r"train\.txt: split 'train' lists no sequence"):
        build_trace_library(root, TraceFilter(min_points=50))


def test_rebuild_with_other_filters_does_not_replace_the_shared_file(tiny_root, tmp_path):
    tool = load_tool("data/build_trace_library")
    yaml = str(REPO_ROOT / "cfgs/attacks/inj_rel_easy.yaml")
    out = tmp_path / "shared.npz"
    base = ["--cfg", yaml, "--data_path", str(tiny_root), "--out", str(out)]
    tool.main(base)
    before = TraceLibrary.load(out)
    tool.main(base)  # the same filters: rebuilt in place, the same library
    again = TraceLibrary.load(out)
    assert again.build_info["filters"]["min_points"] == 200 and len(again.offsets) > 1
    np.testing.assert_array_equal(again.points, before.points)
    np.testing.assert_array_equal(again.offsets, before.offsets)
    before = out.read_bytes()
    other = [*base, "--set", "TRACE_LIBRARY.MIN_POINTS", "100"]
    with pytest.raises(FileExistsError, match=r"shared\.npz holds a trace library built with"):
        tool.main(other)
    assert out.read_bytes() == before
    tool.main([*other[:-3], "--overwrite", *other[-3:]])
    assert TraceLibrary.load(out).build_info["filters"]["min_points"] == 100
    # the same filters for another LIDAR.ORIGIN: the variants sharing the file would stop loading
    moved = tmp_path / "moved.yaml"
    moved.write_text(f"_BASE_CONFIG_: {yaml}\nLIDAR:\n  ORIGIN: [1.0, 0.0, 2.0]\n")
    before = out.read_bytes()
    with pytest.raises(FileExistsError, match=r"'sensor_origin': \[1\.0, 0\.0, 2\.0\]"):
        tool.main(["--cfg", str(moved), *base[2:], "--set", "TRACE_LIBRARY.MIN_POINTS", "100"])
    assert out.read_bytes() == before


def test_a_sequence_pkl_that_would_run_code_is_refused(tmp_path):
    root = write_tiny_waymo(tmp_path / "tiny", frames={"train": 2, "val": 1})
    seq = read_image_set(root / "ImageSets" / "train.txt")[0]
    marker = tmp_path / "marker"
    pkl = malicious_pickle(sequence_pkl_path(root, seq), marker)
    with pytest.raises(RefusedGlobalError, match=rf"{pkl}: refused to unpickle the global "):
        build_trace_library(root, TraceFilter(min_points=50))
    assert not marker.exists()


def test_a_split_leaving_the_data_root_is_refused(tiny_root, tmp_path):
    """``TRACE_LIBRARY.SPLIT`` names ``ImageSets/<SPLIT>.txt``: ``../x`` is refused, naming
    the YAML."""
    yaml = tmp_path / "inj.yaml"
    yaml.write_text(f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs/attacks/inj_rel_easy.yaml'}\n"
                    "TRACE_LIBRARY:\n  SPLIT: ../../x\n")  # fmt: skip
    with pytest.raises(UnsafePathError, match=rf"TRACE_LIBRARY\.SPLIT '\.\./\.\./x' \(from "
                       rf"{re.escape(str(yaml))}\)"):  # fmt: skip
        TraceFilter.from_config(cfg_from_yaml_file(yaml).TRACE_LIBRARY)
    (tiny_root.parent / "x.txt").write_text((tiny_root / "ImageSets" / "train.txt").read_text())
    with pytest.raises(UnsafePathError, match=r"split '\.\./\.\./x' \(from the split of build"):
        build_trace_library(tiny_root, TraceFilter(min_points=50), split="../../x")


@pytest.mark.parametrize("path", ["../outside.npz", "sub/../../outside.npz", "ABSOLUTE"])
def test_the_build_tool_writes_no_library_outside_the_data_root(tiny_root, tmp_path, path):
    """A relative ``TRACE_LIBRARY.PATH`` stays under ``--data_path``; an absolute one is never
    written (``--out`` writes elsewhere, the user's choice): nothing is created outside."""
    path = str(tmp_path / "outside.npz") if path == "ABSOLUTE" else path
    yaml = tmp_path / "inj.yaml"
    yaml.write_text(f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs/attacks/inj_rel_easy.yaml'}\n"
                    f"TRACE_LIBRARY:\n  PATH: {path}\n")  # fmt: skip
    args = ["--cfg", str(yaml), "--data_path", str(tiny_root)]
    with pytest.raises(UnsafePathError, match=rf"TRACE_LIBRARY\.PATH '{re.escape(path)}' \(from "
                       rf"{re.escape(str(yaml))}\)"):  # fmt: skip
        load_tool("data/build_trace_library").main(args)
    assert (
        not (tmp_path / "outside.npz").exists() and not (tiny_root.parent / "outside.npz").exists()
    )


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_library_that_is_not_a_regular_file_is_refused(tmp_path, kind):
    """A FIFO (or a device) would make loading and hashing the library read forever."""
    path = tmp_path / "lib.npz"
    if kind == "fifo":
        os.mkfifo(path)
    else:
        path.mkdir()
    shown = "a FIFO" if kind == "fifo" else "a folder"
    with pytest.raises(UnsafePathError, match=rf"trace library .*lib\.npz is {shown}, not a reg"):
        TraceLibrary.load(path)

import numpy as np
import pytest
import torch

from pcdet_atlas.attacks.lidar_fit import fit_lidar_from_sequence, top_lidar_points
from pcdet_atlas.datasets.waymo_format import (
    data_dir,
    frame_npy_path,
    load_frame_points,
    load_sequence_infos,
    sequence_pkl_path,
)
from pcdet_atlas.ops.lidar_model import LidarModel


def first_sequence(root):
    return sorted(p.name for p in data_dir(root).iterdir() if p.is_dir())[0]


def test_fit_recovers_the_synthetic_sensor_table(synthetic_root):
    """The synthetic sensor casts the default Waymo TOP table; fitting its points recovers it."""
    lidar = fit_lidar_from_sequence(synthetic_root, first_sequence(synthetic_root)).lidar
    truth = LidarModel.waymo_top()
    err = (lidar.inclinations - truth.inclinations).abs()
    spacing = float(torch.diff(truth.inclinations).min())
    assert float(torch.quantile(err, 0.9)) < 0.1 * spacing
    assert lidar.num_beams == 64


def test_fit_follows_a_shifted_sensor(synthetic_root):
    """Tilt every elevation of real scan points by a known offset: the fit must move with it
    (the fit starts from the default table, so this fails if it does nothing)."""
    seq = first_sequence(synthetic_root)
    infos = load_sequence_infos(sequence_pkl_path(synthetic_root, seq))
    pts = np.concatenate(
        [
            top_lidar_points(
                load_frame_points(frame_npy_path(synthetic_root, seq, i)), infos[i], "f"
            )
            for i in range(0, len(infos), 3)
        ]
    )[:, :3].astype(np.float64)
    truth = LidarModel.waymo_top()
    shift = np.deg2rad(0.05)
    rel = pts - truth.origin.numpy()
    horiz = np.hypot(rel[:, 0], rel[:, 1])
    rng = np.linalg.norm(rel, axis=1)
    elev = np.arctan2(rel[:, 2], horiz) + shift
    scale = rng * np.cos(elev) / np.maximum(horiz, 1e-9)
    moved = np.stack([rel[:, 0] * scale, rel[:, 1] * scale, rng * np.sin(elev)], 1)
    fitted = LidarModel.fit(moved + truth.origin.numpy())
    err = (fitted.inclinations - (truth.inclinations + shift)).abs()
    seen = torch.bincount(truth.beam_index(torch.as_tensor(elev - shift)), minlength=64) > 100
    assert seen.sum() > 40  # most beams have returns
    assert float(err[seen].max()) < np.deg2rad(0.005)


def test_top_rows_checked_against_info(synthetic_root):
    seq = first_sequence(synthetic_root)
    infos = load_sequence_infos(sequence_pkl_path(synthetic_root, seq))
    pts = load_frame_points(frame_npy_path(synthetic_root, seq, 0))
    top = top_lidar_points(pts, infos[0], "f")
    assert top.shape[0] == infos[0]["num_points_of_each_lidar"][0]
    with pytest.raises(ValueError, match="sums to"):
        top_lidar_points(np.zeros((3, 6), np.float32), infos[0], "f")
    with pytest.raises(ValueError, match="out of range"):
        fit_lidar_from_sequence(synthetic_root, seq, frames=[10_000])


def test_top_rows_of_a_written_atlas_frame():
    """In a frame of tools/data/generate_atlas.py the TOP count includes the phantom rows, which
    are the last rows of the file (after the other LiDARs' rows)."""
    rows = np.arange(6 * 6, dtype=np.float32).reshape(6, 6)  # TOP 0-1, FRONT 2-4, phantom 5
    info = {"num_points_of_each_lidar": [3, 3, 0, 0, 0], "atlas": {"num_injected_rows": 1}}
    np.testing.assert_array_equal(top_lidar_points(rows, info, "f"), rows[[0, 1, 5]])
    info["atlas"]["num_injected_rows"] = 4
    with pytest.raises(ValueError, match="num_injected_rows = 4"):
        top_lidar_points(rows, info, "f")


def _fit_cli(root, *args) -> str:
    import subprocess
    import sys

    from pcdet_atlas.config import REPO_ROOT

    run = subprocess.run(
        [sys.executable, str(REPO_ROOT / "tools" / "data" / "fit_lidar_model.py"), "--data_path",
         str(root), "--sequence", first_sequence(root), "--frames", "0", "3", *args],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout


def test_fit_cli_estimates_the_bins_and_warns_on_a_wrong_origin(synthetic_root):
    """The synthetic sensor (Waymo TOP table, 2651 columns, at Waymo's mount): the CLI recovers
    its columns with no warning; measured from the vehicle origin it warns and says why."""
    import yaml

    out = _fit_cli(synthetic_root, "--estimate_azimuth_bins")
    assert "azimuth bins estimated: 2651" in out and "WARNING" not in out
    lidar = LidarModel.from_config(yaml.safe_load(out)["LIDAR"])
    err = (lidar.inclinations - LidarModel.waymo_top().inclinations).abs().max()
    assert float(err) < np.deg2rad(0.01)
    wrong = _fit_cli(synthetic_root, "--origin", "0", "0", "0", "--azimuth_bins", "2651")
    assert "WARNING" in wrong and "--origin" in wrong

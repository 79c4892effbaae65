"""``--save_to_file``'s prediction files in a resumed (received) evaluation folder."""

import numpy as np
import pytest

from pcdet_atlas.train_utils.eval_utils import write_prediction_files
from pcdet_atlas.utils.paths import UnsafePathError

VICTIM_TEXT = "IMPORTANT USER DATA\n"


def _annos(*frame_ids):
    return [{"frame_id": fid, "name": np.array(["Vehicle"]), "boxes_lidar": np.zeros((1, 7)),
             "score": np.array([0.9])} for fid in frame_ids]  # fmt: skip


def test_a_prediction_file_symlinked_out_of_the_folder_is_refused_before_any_write(tmp_path):
    """The name checked is the name written (``<frame_id>.txt``): a planted link there that
    leads out of the folder is an error naming it, and nothing is written."""
    victim = tmp_path / "victim.txt"
    victim.write_text(VICTIM_TEXT)
    out = tmp_path / "eval" / "clean" / "final_result" / "data"
    out.mkdir(parents=True)
    (out / "seq_001.txt").symlink_to(victim)
    with pytest.raises(UnsafePathError, match=r"seq_001\.txt \(from prediction 1\) resolves to "
                       rf".*victim\.txt, outside its root {out}"):  # fmt: skip
        write_prediction_files(_annos("seq_000", "seq_001"), out)
    assert victim.read_text() == VICTIM_TEXT
    assert sorted(p.name for p in out.iterdir()) == ["seq_001.txt"]  # checked before any write


def test_a_prediction_file_symlinked_inside_the_folder_is_replaced_not_followed(tmp_path):
    out = tmp_path / "data"
    out.mkdir()
    (out / "other.txt").write_text("another frame's boxes\n")
    (out / "seq_000.txt").symlink_to(out / "other.txt")
    write_prediction_files(_annos("seq_000"), out)
    assert (out / "other.txt").read_text() == "another frame's boxes\n"
    assert not (out / "seq_000.txt").is_symlink()
    assert (out / "seq_000.txt").read_text() == (
        "Vehicle 0.0000 0.0000 0.0000 0.0000 0.0000 0.0000 0.0000 0.9000\n"
    )
    assert sorted(p.name for p in out.iterdir()) == ["other.txt", "seq_000.txt"]

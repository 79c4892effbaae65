"""`make demo`: the embedded default end to end.

For now: generate the default synthetic Waymo-format dataset at ``data/synthetic_waymo`` (if it is
not there yet; a finished dataset is reused as is) and print a summary of it.
"""

from __future__ import annotations

import os

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.datasets.synthetic import create_synthetic_waymo, format_summary
from pcdet_atlas.utils.common import create_logger

SYNTHETIC_ROOT = REPO_ROOT / "data" / "synthetic_waymo"


def main() -> dict:
    logger = create_logger()
    logger.info("synthetic dataset: %s (default size, seed 0)", SYNTHETIC_ROOT)
    summary = create_synthetic_waymo(
        SYNTHETIC_ROOT, seed=0, logger=logger, workers=min(2, os.cpu_count() or 1)
    )
    print(format_summary(summary))
    if summary["generated"] == 0:
        print("  (already generated earlier: nothing rewritten)")
    return summary


if __name__ == "__main__":
    main()

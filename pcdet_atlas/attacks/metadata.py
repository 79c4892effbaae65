"""The per-frame attack metadata record (the ``attack`` key of ``AtlasWaymoDataset`` samples).

One plain dict per frame, consumed by the evaluation (ASR, confidence, lifecycle)::

    {'variant': str, 'family': 'clean' | 'injection' | 'removal' | <new family>,
     'spoofed': bool,            # the schedule spoofs this frame
     'run_id': int,              # the run this frame is spoofed by, or (clean lifecycle frames)
                                 #   whose shadow it carries; -1 otherwise
     'run_position': int,        # 0-based index within the run, -1 if not in a run
     'lifecycle_k': int,         # 0 = last clean frame before onset, 1..W spoofed,
                                 #   W+1..2W clean frames after the run, -1 otherwise
     'target_box': np.float32 (7,) or None,  # phantom box (injection) / tracked + fired target
                                 #   (removal); on shadow frames the continued phantom / target
     'target_is_shadow': bool,   # True on clean lifecycle frames that carry a shadow target
                                 #   (the target_box is then set)
     'target_obj_id': str or None,
     'num_spoof_points': int,    # phantom points fed to the raycaster (injection)
     'num_visible': int,         # phantom points that survived the raycast (injection)
     'num_removed': int,         # scene points removed (occluded by the phantom / A-HFR)
     'tracked': bool, 'fired': bool}

``run_id`` / ``lifecycle_k`` come from :mod:`pcdet_atlas.attacks.schedule`; where a frame is in
two lifecycles (``k = 2W`` of one run and ``k = 0`` of the next) the upcoming run's onset is kept.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["META_KEYS", "make_meta", "validate_meta"]

META_KEYS = (
    "variant",
    "family",
    "spoofed",
    "run_id",
    "run_position",
    "lifecycle_k",
    "target_box",
    "target_is_shadow",
    "target_obj_id",
    "num_spoof_points",
    "num_visible",
    "num_removed",
    "tracked",
    "fired",
)


def make_meta(
    variant: str,
    family: str,
    spoofed: bool = False,
    run_id: int = -1,
    run_position: int = -1,
    lifecycle_k: int = -1,
    target_box: np.ndarray | None = None,
    target_is_shadow: bool = False,
    target_obj_id: str | None = None,
    num_spoof_points: int = 0,
    num_visible: int = 0,
    num_removed: int = 0,
    tracked: bool = False,
    fired: bool = False,
) -> dict[str, Any]:
    """A metadata dict with every key of the schema, values cast to plain Python / float32."""
    box = None
    if target_box is not None:
        box = np.asarray(target_box, dtype=np.float32).reshape(-1)[:7].copy()
        if box.shape != (7,) or not np.isfinite(box).all():
            raise ValueError(f"target_box must be 7 finite values, got {target_box!r}")
    return {
        "variant": str(variant),
        "family": str(family),
        "spoofed": bool(spoofed),
        "run_id": int(run_id),
        "run_position": int(run_position),
        "lifecycle_k": int(lifecycle_k),
        "target_box": box,
        "target_is_shadow": bool(target_is_shadow),
        "target_obj_id": None if target_obj_id is None else str(target_obj_id),
        "num_spoof_points": int(num_spoof_points),
        "num_visible": int(num_visible),
        "num_removed": int(num_removed),
        "tracked": bool(tracked),
        "fired": bool(fired),
    }


def validate_meta(meta: dict, where: str = "attack metadata") -> None:
    """Raise ``ValueError`` naming the key if ``meta`` does not follow the schema."""
    missing = [k for k in META_KEYS if k not in meta]
    extra = [k for k in meta if k not in META_KEYS]
    if missing or extra:
        raise ValueError(f"{where}: missing keys {missing}, unexpected keys {extra}")
    box = meta["target_box"]
    if box is not None and (
        not isinstance(box, np.ndarray) or box.dtype != np.float32 or box.shape != (7,)
    ):
        raise ValueError(f"{where}: target_box must be None or float32 (7,), got {box!r}")
    if meta["target_is_shadow"] and meta["spoofed"]:
        raise ValueError(f"{where}: a spoofed frame cannot carry a shadow target")
    if meta["target_is_shadow"] and box is None:
        raise ValueError(f"{where}: target_is_shadow is True but target_box is None")
    if box is not None and not (meta["spoofed"] or meta["target_is_shadow"]):
        raise ValueError(f"{where}: target_box on a frame neither spoofed nor shadow")
    if meta["spoofed"] != (meta["run_position"] >= 0):
        raise ValueError(
            f"{where}: spoofed={meta['spoofed']} but run_position={meta['run_position']}"
        )
    if meta["run_position"] >= 0 and meta["run_id"] < 0:
        raise ValueError(f"{where}: run_position={meta['run_position']} without a run_id")

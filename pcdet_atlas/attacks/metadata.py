"""The per-frame attack metadata record (the ``attack`` key of ``AtlasWaymoDataset`` samples).

One plain dict per frame, consumed by the evaluation (ASR, confidence, lifecycle)::

    {'variant': str, 'family': 'clean' | 'injection' | 'removal' | <new family>,
     'sequence_name': str or None,  # the frame's sequence (set by AtlasWaymoDataset)
     'spoofed': bool,            # the schedule spoofs this frame
     'run_id': int,              # the run this frame is spoofed by, or (clean lifecycle frames)
                                 #   whose shadow it carries; -1 otherwise; runs are numbered
                                 #   per sequence, so a run is (sequence_name, run_id)
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
     'tracked': bool, 'fired': bool,
     # how the evaluation scores this family, from the attack class (docs/attacks.md):
     'success_if_detected': bool or None,  # a target counts as a success when detected (True,
                                 #   e.g. a phantom) or when missed (False); None: no targets
     'confidence': str or None,  # the confidence kind of its targets: 'injection', 'removal'
                                 #   or one registered with the evaluation's
                                 #   analyses.register_confidence_kind (None: none)
     'rank_group': str or None,  # robustness-rank group of the variant (None: not ranked)
     <registered key>: ...}      # a key a family adds with register_meta_key (its default on
                                 #   every frame of the other families)

``run_id`` / ``lifecycle_k`` come from :mod:`pcdet_atlas.attacks.schedule`; where a frame is in
two lifecycles (``k = 2W`` of one run and ``k = 0`` of the next) the upcoming run's onset is kept.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "CONFIDENCE_ANALYSES",
    "META_KEYS",
    "make_meta",
    "meta_keys",
    "register_meta_key",
    "validate_meta",
]

META_KEYS = (
    "variant",
    "family",
    "sequence_name",
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
    "success_if_detected",
    "confidence",
    "rank_group",
)

#: The built-in confidence kinds (``evaluation.analyses.confidence``: ``injection``, the scores of
#: the detected targets; ``removal``, surviving targets vs the clean run). A family may name
#: another kind registered with the evaluation; scoring an unregistered one is an error there.
CONFIDENCE_ANALYSES = ("injection", "removal")
#: Keys families added to the record (:func:`register_meta_key`): name -> default.
_EXTRA_KEYS: dict[str, Any] = {}


def register_meta_key(name: str, default: Any = None) -> None:
    """Add ``name`` to every frame's metadata record (``default`` where the family does not set
    it): a new family records what its analysis reads, as ``self.meta(state, name=value)``.
    A name of the schema, or one registered with another default, raises naming it."""
    if not name or not isinstance(name, str):
        raise ValueError(f"a metadata key must be a non-empty string, got {name!r}")
    if name in META_KEYS or (name in _EXTRA_KEYS and _EXTRA_KEYS[name] != default):
        raise ValueError(f"metadata key {name!r} is registered already")
    _EXTRA_KEYS[name] = default


def meta_keys() -> tuple[str, ...]:
    """Every key of a record: :data:`META_KEYS` and the registered ones, in that order."""
    return META_KEYS + tuple(_EXTRA_KEYS)


def make_meta(
    variant: str,
    family: str,
    spoofed: bool = False,
    sequence_name: str | None = None,
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
    success_if_detected: bool | None = None,
    confidence: str | None = None,
    rank_group: str | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """A metadata dict with every key of the schema, values cast to plain Python / float32;
    ``extra``: values of registered keys (:func:`register_meta_key`), the others default."""
    unknown = sorted(set(extra) - set(_EXTRA_KEYS))
    if unknown:
        raise ValueError(
            f"metadata keys {unknown} are not registered (register_meta_key); registered: "
            f"{sorted(_EXTRA_KEYS)}"
        )
    box = None
    if target_box is not None:
        box = np.asarray(target_box, dtype=np.float32).reshape(-1)[:7].copy()
        if box.shape != (7,) or not np.isfinite(box).all():
            raise ValueError(f"target_box must be 7 finite values, got {target_box!r}")
    return {
        "variant": str(variant),
        "family": str(family),
        "sequence_name": None if sequence_name is None else str(sequence_name),
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
        "success_if_detected": None if success_if_detected is None else bool(success_if_detected),
        "confidence": None if confidence is None else str(confidence),
        "rank_group": None if rank_group is None else str(rank_group),
        **{key: extra.get(key, default) for key, default in _EXTRA_KEYS.items()},
    }


def validate_meta(meta: dict, where: str = "attack metadata") -> None:
    """Raise ``ValueError`` naming the key if ``meta`` does not follow the schema."""
    keys = meta_keys()
    missing = [k for k in keys if k not in meta]
    extra = [k for k in meta if k not in keys]
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
    if box is not None and meta["success_if_detected"] is None:
        raise ValueError(
            f"{where}: a target_box of family {meta['family']!r} needs success_if_detected "
            "(the attack class's SUCCESS_IF_DETECTED)"
        )
    if meta["confidence"] is not None and not (
        isinstance(meta["confidence"], str) and meta["confidence"]
    ):
        raise ValueError(
            f"{where}: confidence {meta['confidence']!r} is not None or the name of a confidence "
            f"kind (built in: {CONFIDENCE_ANALYSES})"
        )
    if meta["run_position"] >= 0 and meta["run_id"] < 0:
        raise ValueError(f"{where}: run_position={meta['run_position']} without a run_id")

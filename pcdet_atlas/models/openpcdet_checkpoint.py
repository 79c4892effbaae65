"""OpenPCDet checkpoints of CenterPoint / CP4F (voxel or pillar) -> this project's ``model_state``.

The mapping is built from the model the matching config builds, so it knows every tensor's name,
shape and kind:

- **Names.** Most stages use OpenPCDet's names (VFE ``pfn_layers``, ``backbone_3d``,
  ``backbone_2d``, ``shared_conv``). A stage whose names differ says so itself with an
  ``openpcdet_names()`` method (:meth:`CenterHead.openpcdet_names`). OpenPCDet's
  ``global_step`` (its step counter) is dropped; a buffer that OpenPCDet does not save (the
  head's ``code_weights``) is taken from the config.
- **Sparse conv weights.** Ours have spconv 2.x's default layout ``(out, kD, kH, kW, in)``.
  A checkpoint trained with spconv 1.x holds ``(kD, kH, kW, in, out)``, and spconv 2.x's
  native algorithm ``(kD, kH, kW, out, in)`` (OpenPCDet's own loader converts both). A
  checkpoint has a single layout. It is read from the weights whose shape fits only one layout,
  or given by the caller when every weight is ambiguous (``in == out`` for all of them).
- **Mismatches.** Unknown keys, missing keys and wrong shapes raise one
  :class:`CheckpointMismatchError` that names them.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from pcdet_atlas.models.detectors.detector3d_template import (
    CheckpointMismatchError,
    read_checkpoint,
)
from pcdet_atlas.ops.spconv import SparseConv3d, SubMConv3d
from pcdet_atlas.version import __version__

__all__ = [
    "OPENPCDET_IGNORED_KEYS",
    "SPCONV_LAYOUTS",
    "atlas_to_openpcdet_state",
    "convert_openpcdet_checkpoint",
    "detect_spconv_layout",
    "openpcdet_key_map",
    "openpcdet_to_atlas_state",
    "spconv_weight_keys",
]

#: keys of OpenPCDet's ``model_state`` that hold no weights of the model
OPENPCDET_IGNORED_KEYS = ("global_step",)

#: sparse conv weight layouts: name -> (axis order as described, permutation from ours
#: ``(out, kD, kH, kW, in)`` to it)
SPCONV_LAYOUTS: dict[str, tuple[str, tuple[int, ...]]] = {
    "spconv2": ("(out, kD, kH, kW, in), spconv 2.x default (KRSC)", (0, 1, 2, 3, 4)),
    "spconv2-native": ("(kD, kH, kW, out, in), spconv 2.x native algorithm", (1, 2, 3, 0, 4)),
    "spconv1": ("(kD, kH, kW, in, out), spconv 1.x", (1, 2, 3, 4, 0)),
}


def _inverse(perm: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(sorted(range(len(perm)), key=lambda i: perm[i]))


def _format(problems: list[str]) -> str:
    head = "; ".join(problems[:10])
    return head + (f"; ... ({len(problems)} in all)" if len(problems) > 10 else "")


def _describe(kind: str, keys: list[str]) -> list[str]:
    """Up to 10 keys by name; more, counted per stage with the first of each (a checkpoint of
    another architecture differs in hundreds of keys)."""
    if len(keys) <= 10:
        return [f"{kind} {k}" for k in keys]
    stages: dict[str, list[str]] = {}
    for key in keys:
        stages.setdefault(key.split(".")[0], []).append(key)
    per_stage = ", ".join(f"{len(v)} under {s} (first {v[0]})" for s, v in stages.items())
    return [f"{len(keys)} {kind} keys: {per_stage}"]


def openpcdet_key_map(model: nn.Module) -> dict[str, str | None]:
    """Every key of ``model.state_dict()`` -> OpenPCDet's name of that tensor (``None``: OpenPCDet
    does not save it; the value comes from the config)."""
    out: dict[str, str | None] = {}
    for stage_name, stage in model.named_children():
        own = (
            stage.openpcdet_names()
            if hasattr(stage, "openpcdet_names")
            else {key: key for key in stage.state_dict()}
        )
        for key, theirs in own.items():
            out[f"{stage_name}.{key}"] = None if theirs is None else f"{stage_name}.{theirs}"
    missing = set(model.state_dict()) - set(out)
    if missing:  # a tensor registered on the detector itself, outside every stage
        raise ValueError(f"{type(model).__name__}: no OpenPCDet name for {sorted(missing)}")
    return out


def spconv_weight_keys(model: nn.Module) -> list[str]:
    """The ``state_dict`` keys of the sparse conv weights of ``model``."""
    return [
        f"{name}.weight"
        for name, module in model.named_modules()
        if isinstance(module, (SubMConv3d, SparseConv3d))
    ]


def _layout_candidates(shape: tuple[int, ...], ours: tuple[int, ...]) -> set[str]:
    return {
        name
        for name, (_, perm) in SPCONV_LAYOUTS.items()
        if tuple(ours[i] for i in perm) == tuple(shape)
    }


def detect_spconv_layout(
    shapes: Mapping[str, tuple[tuple[int, ...], tuple[int, ...]]], source: str
) -> str | None:
    """The one layout of :data:`SPCONV_LAYOUTS` that fits every sparse conv weight.

    Args:
        shapes: OpenPCDet's key -> (its shape in the checkpoint, our model's shape).
        source: the checkpoint's name in error messages.

    Returns:
        The layout's name; ``None`` when ``shapes`` is empty (no sparse convs).

    Raises:
        CheckpointMismatchError: a weight fits no layout, two weights fit different ones, or
            every weight fits several (then the caller must name it: ``spconv_layout``).
    """
    possible = set(SPCONV_LAYOUTS)
    decided_by = None
    problems = []
    for key, (shape, ours) in shapes.items():
        fits = _layout_candidates(tuple(shape), tuple(ours))
        if not fits:
            problems.append(f"{key}: checkpoint {tuple(shape)} fits no sparse conv layout of "
                            f"model {tuple(ours)}")  # fmt: skip
        elif not possible & fits and not problems:
            raise CheckpointMismatchError(
                f"checkpoint {source}: its sparse conv weights fit different layouts ({key} "
                f"{tuple(shape)}: {sorted(fits)}; {decided_by[0]} {decided_by[1]}: "
                f"{sorted(possible)}); a checkpoint has one"
            )
        else:
            possible &= fits
            if len(fits) == 1 and decided_by is None:
                decided_by = (key, tuple(shape))
    if problems:
        raise CheckpointMismatchError(f"checkpoint {source}: {_format(problems)}")
    if not shapes:
        return None
    if len(possible) > 1:
        raise CheckpointMismatchError(
            f"checkpoint {source}: every sparse conv weight has in == out channels, so its "
            f"layout is one of {sorted(possible)}; name it (spconv_layout / --spconv_layout)"
        )
    return possible.pop()


def openpcdet_to_atlas_state(
    state: Mapping[str, torch.Tensor],
    model: nn.Module,
    *,
    spconv_layout: str | None = None,
    source: str = "<state_dict>",
) -> tuple[dict[str, torch.Tensor], str | None]:
    """An OpenPCDet ``model_state`` -> the ``state_dict`` that ``model`` loads strictly.

    Args:
        state: OpenPCDet's names and layouts.
        model: built from the config matching the checkpoint (its names, shapes, config buffers).
        spconv_layout: a key of :data:`SPCONV_LAYOUTS`, or ``None`` to read it from the shapes.
        source: the checkpoint's name in error messages.

    Returns:
        ``(state_dict, layout)``: our names and layouts; the sparse conv layout found (``None``
        for a model without sparse convs).

    Raises:
        CheckpointMismatchError: naming unknown, missing and wrongly shaped keys.
    """
    if spconv_layout is not None and spconv_layout not in SPCONV_LAYOUTS:
        raise ValueError(
            f"spconv_layout {spconv_layout!r}: expected one of {sorted(SPCONV_LAYOUTS)}"
        )
    own = model.state_dict()
    names = openpcdet_key_map(model)
    ours_of = {theirs: ours for ours, theirs in names.items() if theirs is not None}
    sparse = set(spconv_weight_keys(model))
    unknown = sorted(set(state) - set(ours_of) - set(OPENPCDET_IGNORED_KEYS))
    missing = sorted(theirs for theirs in ours_of if theirs not in state)
    problems = _describe("unexpected", unknown) + _describe("missing", missing)
    if any(".heads_list.1." in k for k in unknown):
        problems.append(
            "(the checkpoint has several CenterHead heads, one per CLASS_NAMES_EACH_HEAD group; "
            "this project has one head over all classes)"
        )
    if problems:
        raise CheckpointMismatchError(
            f"checkpoint {source} does not match {type(model).__name__} built from the config: "
            f"{_format(problems)}"
        )
    if spconv_layout is None:
        shapes = {names[k]: (tuple(state[names[k]].shape), tuple(own[k].shape)) for k in sparse}
        layout = detect_spconv_layout(dict(sorted(shapes.items())), source)
    else:
        layout = spconv_layout if sparse else None
    out: dict[str, torch.Tensor] = {}
    bad_shape = []
    for ours, theirs in names.items():
        if theirs is None:  # from the config
            out[ours] = own[ours].clone()
            continue
        value = state[theirs]
        if ours in sparse:
            perm = SPCONV_LAYOUTS[layout][1]
            expected = tuple(own[ours].shape[i] for i in perm)
            if tuple(value.shape) != expected:
                bad_shape.append(
                    f"{theirs}: checkpoint {tuple(value.shape)} vs {expected} in layout "
                    f"{layout} = {SPCONV_LAYOUTS[layout][0]}"
                )
                continue
            value = value.permute(*_inverse(perm)).contiguous()
        elif tuple(value.shape) != tuple(own[ours].shape):
            bad_shape.append(
                f"{theirs}: checkpoint {tuple(value.shape)} vs model {tuple(own[ours].shape)}"
            )
            continue
        out[ours] = value
    if bad_shape:
        raise CheckpointMismatchError(
            f"checkpoint {source} does not match {type(model).__name__} built from the config: "
            f"{_format(bad_shape)}"
        )
    return out, layout


def atlas_to_openpcdet_state(
    state: Mapping[str, torch.Tensor], model: nn.Module, *, spconv_layout: str = "spconv2"
) -> dict[str, torch.Tensor]:
    """The inverse of :func:`openpcdet_to_atlas_state`: our ``state_dict`` (of ``model``'s
    architecture) under OpenPCDet's names, sparse conv weights in ``spconv_layout``, with a
    zero ``global_step``."""
    if spconv_layout not in SPCONV_LAYOUTS:
        raise ValueError(
            f"spconv_layout {spconv_layout!r}: expected one of {sorted(SPCONV_LAYOUTS)}"
        )
    names = openpcdet_key_map(model)
    missing = sorted(set(names) - set(state))
    if missing:
        raise CheckpointMismatchError(f"state_dict lacks {_format(missing)}")
    sparse = set(spconv_weight_keys(model))
    perm = SPCONV_LAYOUTS[spconv_layout][1]
    out = {"global_step": torch.zeros(1, dtype=torch.int64)}
    for ours, theirs in names.items():
        if theirs is not None:
            value = state[ours]
            out[theirs] = value.permute(*perm).contiguous() if ours in sparse else value
    return out


def convert_openpcdet_checkpoint(
    src: str | Path,
    dst: str | Path,
    model: nn.Module,
    *,
    spconv_layout: str | None = None,
) -> dict:
    """Read OpenPCDet's checkpoint ``src``, map it onto ``model`` and write ``dst``.

    ``dst`` holds ``model_state`` (loads strictly into ``model``), OpenPCDet's ``epoch`` and
    ``it`` when present, ``version`` and ``converted_from`` (the source file, its ``version``
    and the sparse conv layout found). Returns that dict.
    """
    ckpt = read_checkpoint(src)
    if "model_state" not in ckpt:
        raise CheckpointMismatchError(
            f"checkpoint {src} has no 'model_state' (keys: {sorted(ckpt)[:10]}); OpenPCDet "
            "saves the weights under that key"
        )
    state, layout = openpcdet_to_atlas_state(
        ckpt["model_state"], model, spconv_layout=spconv_layout, source=str(src)
    )
    out = {k: ckpt[k] for k in ("epoch", "it") if ckpt.get(k) is not None}
    out.update(
        model_state=state,
        version=f"pcdet_atlas+{__version__}",
        converted_from={
            "file": str(src),
            "version": ckpt.get("version"),
            "spconv_layout": layout,
        },
    )
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    torch.save(out, dst)
    return out

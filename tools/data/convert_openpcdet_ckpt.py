"""Convert an OpenPCDet checkpoint (CenterPoint / CP4F, DSVT, or MSF's second stage) to ours.

    python tools/data/convert_openpcdet_ckpt.py --cfg cfgs/atlas/cp4f_voxel.yaml \
        --ckpt /path/to/openpcdet/checkpoint_epoch_36.pth --out checkpoints/cp4f_voxel_waymo.pth

``--cfg`` is the config whose model the checkpoint was trained as (``centerpoint_voxel.yaml`` for
OpenPCDet's ``centerpoint.yaml``, ``cp4f_voxel.yaml`` for ``centerpoint_4frames.yaml``; the
pillar configs for ``centerpoint_dyn_pillar_1x.yaml``, ``dsvt.yaml`` for ``dsvt_voxel.yaml``;
``msf_4f.yaml``, its ``MODEL.RPN`` naming the converted CP4F that proposed for it, for
``msf_4frames.yaml``). The written file loads
strictly into that model (checked before the tool ends); pass it to ``tools/test.py --ckpt``.
A two-stage checkpoint records the config's RPN checkpoint as the one it was trained with. Sparse
conv weights of spconv 1.x or 2.x are recognised by their shapes; ``--spconv_layout`` names the
layout when the shapes cannot tell (docs/getting_started.md). A PTT checkpoint of the PTT
repository does not convert: part of its head has no counterpart here (the error names it).
The checkpoint is read with ``torch.load(weights_only=True)`` (tensors and plain values; the
numpy scalars of OpenPCDet's optimizer state allowed), and NaN/inf weights are refused, naming
the tensor.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from pcdet_atlas.config import cfg_from_list, cfg_from_yaml_file
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.models.openpcdet_checkpoint import SPCONV_LAYOUTS, convert_openpcdet_checkpoint
from pcdet_atlas.utils.cli import add_debug_flag, add_set_flag, run_tool


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_debug_flag(parser)
    parser.add_argument("--cfg_file", "--cfg", dest="cfg_file", required=True, help="model YAML")
    parser.add_argument("--ckpt", required=True, help="OpenPCDet checkpoint (.pth)")
    parser.add_argument("--out", required=True, help="converted checkpoint to write")
    parser.add_argument(
        "--spconv_layout", choices=sorted(SPCONV_LAYOUTS), default=None,
        help="layout of the sparse conv weights (default: read from their shapes)",
    )  # fmt: skip
    parser.add_argument(
        "--overwrite", action="store_true", default=False, help="replace an existing --out"
    )
    add_set_flag(parser, help="KEY VALUE pairs overriding the config")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"{out} exists: pass --overwrite to replace it")
    if out.resolve() == Path(args.ckpt).resolve():
        raise ValueError(f"--out {out} is the input checkpoint; write the conversion elsewhere")
    cfg = cfg_from_yaml_file(args.cfg_file)
    if args.set_cfgs:
        cfg_from_list(args.set_cfgs, cfg)
    model = build_network_from_config(cfg)
    # written beside --out and loaded strictly (the promise of this tool) before it takes the
    # name: a failed check or a kill leaves no --out that a rerun would have to --overwrite
    staged = out.with_name(f".{out.name}.unchecked")
    try:
        written = convert_openpcdet_checkpoint(
            args.ckpt, staged, model, spconv_layout=args.spconv_layout
        )
        model.load_params_from_file(staged, strict=True)
        os.replace(staged, out)
    finally:
        staged.unlink(missing_ok=True)
    source = written["converted_from"]
    rpn = written.get("model_info", {}).get("rpn")
    print(
        f"{args.ckpt} ({source['version'] or 'no version'}, epoch {written.get('epoch', '?')}) "
        f"-> {out}: {len(written['model_state'])} tensors of {type(model).__name__} "
        f"({args.cfg_file}), sparse conv layout {source['spconv_layout'] or '-'}"
        + (f", RPN {rpn['checkpoint']} recorded" if rpn else "")
        + "; loads strictly"
    )
    return out


if __name__ == "__main__":
    run_tool(main)

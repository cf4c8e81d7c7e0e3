"""``geoseg export``: write a trained (or randomly initialised) network to ONNX."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

logger = logging.getLogger(__name__)

MAX_SIDE = 8192  # the largest image side of the exported graphs (geoseg.export)


def configure(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", type=Path, help="model checkpoint (.pt) to export")
    source.add_argument(
        "--model",
        help="registry name (enet, joint, naive_cnn, reloc, relpose): export random weights",
    )
    parser.add_argument("--out", type=Path, required=True, help="output .onnx file")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --out file that is not a geoseg ONNX export",
    )
    parser.add_argument(
        "--config",
        default=None,
        help="with --model: builder options as JSON, e.g. '{\"num_classes\": 8}'",
    )
    parser.add_argument("--seed", type=int, default=None, help="with --model: weight seed (0)")
    parser.add_argument("--height", type=int, default=64, help="example input height (pixels)")
    parser.add_argument("--width", type=int, default=48, help="example input width (pixels)")
    parser.add_argument(
        "--static", action="store_true", help="fixed input size instead of dynamic batch/size"
    )


def _is_geoseg_onnx(path: Path) -> bool:
    """True when ``path`` is an ONNX file written by geoseg (it carries ``geoseg.*`` metadata)."""
    try:
        import onnx

        proto = onnx.load(str(path), load_external_data=False)
    except Exception:  # not ONNX at all
        return False
    return any(p.key.startswith("geoseg.") for p in proto.metadata_props)


def run(args: argparse.Namespace) -> int:
    import torch

    from geoseg.errors import GeosegError
    from geoseg.export import OnnxModel, default_example_inputs, export_onnx, prepare_for_export
    from geoseg.infer import DEFAULT_NORMALIZATION, load_model_checkpoint
    from geoseg.models.registry import get_model
    from geoseg.output_dir import prepare_output_file

    if not (1 <= args.height <= MAX_SIDE and 1 <= args.width <= MAX_SIDE):
        raise GeosegError(
            f"--height/--width: expected 1..{MAX_SIDE} pixels, got {args.height}x{args.width}"
        )
    if args.checkpoint is not None and (args.config is not None or args.seed is not None):
        raise GeosegError("--config/--seed: only with --model (a checkpoint has its own)")
    if args.seed is not None and not 0 <= args.seed < 2**63:
        raise GeosegError(f"--seed: expected an integer in [0, 2**63), got {args.seed}")
    out = prepare_output_file(args.out, overwrite=args.overwrite, owned=_is_geoseg_onnx)
    if args.checkpoint is not None:
        model, ckpt = load_model_checkpoint(args.checkpoint)
        name, config = str(ckpt["model_name"]), dict(ckpt.get("model_config") or {})
        normalization = ckpt.get("normalization") or DEFAULT_NORMALIZATION
    else:
        try:
            config = json.loads(args.config or "{}")
        except json.JSONDecodeError as err:
            raise GeosegError(f"--config: not valid JSON ({err})") from None
        if not isinstance(config, dict):
            raise GeosegError(f"--config: expected a JSON object, got {args.config!r}")
        torch.manual_seed(args.seed or 0)
        name, normalization = args.model, DEFAULT_NORMALIZATION
        model = get_model(name, **config)
    model = prepare_for_export(model.eval())
    inputs = default_example_inputs(model, height=args.height, width=args.width)
    path = export_onnx(
        model,
        out,
        example_inputs=inputs,
        dynamic=not args.static,
        metadata={"model_name": name, "model_config": config, "normalization": normalization},
    )
    onnx_model = OnnxModel(path, providers=["CPUExecutionProvider"])
    outputs = onnx_model(*[x.numpy() for x in inputs])
    shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in outputs.items())
    print(f"wrote {path} ({name}; inputs {onnx_model.input_names}; outputs {shapes})")
    return 0

"""Where onnxruntime's time goes: per-operator kernel times from its profiler, and MAC counts.

Used by ``bench/inference_speed.py`` (figures ``ops_<model>_<Op>_ms``, ``<model>_gmac_640x480``)
and on its own::

    python bench/ort_operators.py model.onnx [other.onnx ...] --threads 2

Kernel times are onnxruntime's own (``SessionOptions.enable_profiling``; events ``*_kernel_time``),
summed per operator type for each call, then the median over the calls after the warm-up. They
add up to less than the wall time (the executor's own work between the kernels is not in them),
and a loaded CPU inflates them as it does the wall time: compare operators within one run.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np


def operator_breakdown(
    path: str | os.PathLike,
    *,
    threads: int,
    fixed_dims: Mapping[str, int] | None = None,
    calls: int = 8,
    warmup: int = 2,
    seed: int = 0,
) -> dict[str, float]:
    """Median per-call kernel milliseconds of each operator type of the ONNX model at ``path``.

    Args:
        path: an ONNX file with one float input.
        threads: onnxruntime intra-op threads.
        fixed_dims: symbolic input dimensions to fix (as ``OnnxModel(fixed_dims=...)``).
        calls: profiled calls after ``warmup`` unprofiled-in-the-figures ones.
        seed: the random input's.

    Returns:
        ``{op type: ms}``, largest first, plus ``"TOTAL"`` (the sum of the kernel times).
    """
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.add_session_config_entry("session.force_spinning_stop", "1")
    for name, size in (fixed_dims or {}).items():
        options.add_free_dimension_override_by_name(name, int(size))
    with tempfile.TemporaryDirectory() as tmp:
        options.enable_profiling = True
        options.profile_file_prefix = str(Path(tmp) / "ort")
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        inp = session.get_inputs()[0]
        shape = [d if isinstance(d, int) else (fixed_dims or {}).get(d, 1) for d in inp.shape]
        x = np.random.default_rng(seed).standard_normal(shape).astype(np.float32)
        for _ in range(warmup + calls):
            session.run(None, {inp.name: x})
        events = json.loads(Path(session.end_profiling()).read_text())
    runs = sorted((e["ts"], e["ts"] + e["dur"]) for e in events if e.get("name") == "model_run")
    per_call: dict[str, list[float]] = collections.defaultdict(list)
    kernels = [e for e in events if e.get("cat") == "Node" and e["name"].endswith("_kernel_time")]
    for start, end in runs[warmup:]:
        sums: collections.Counter[str] = collections.Counter()
        for e in kernels:
            if start <= e["ts"] <= end:
                sums[e["args"]["op_name"]] += e["dur"] / 1000.0
        sums["TOTAL"] = sum(sums.values())
        for op in set(sums) | set(per_call):
            per_call[op].append(sums.get(op, 0.0))
    medians = {op: statistics.median(v) for op, v in per_call.items()}
    return dict(sorted(medians.items(), key=lambda kv: -kv[1]))


def count_macs(model, x) -> int:
    """Multiply-accumulates of ``model(x)``'s convolutions (plain and transposed), which hold
    nearly all of ENet's and LRASPP's arithmetic."""
    import torch

    total = [0]

    def hook(module, inputs, output) -> None:
        if isinstance(module, torch.nn.Conv2d):
            total[0] += output.numel() * module.weight.numel() // module.out_channels
        elif isinstance(module, torch.nn.ConvTranspose2d):
            total[0] += inputs[0].numel() * module.weight.numel() // module.in_channels

    handles = [m.register_forward_hook(hook) for m in model.modules()]
    try:
        with torch.inference_mode():
            model(x)
    finally:
        for handle in handles:
            handle.remove()
    return total[0]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", type=Path)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--size", type=int, nargs=2, default=(480, 640), metavar=("H", "W"))
    args = parser.parse_args(argv)
    dims = {"batch": 1, "height": args.size[0], "width": args.size[1]}
    tables = {
        p.stem: operator_breakdown(p, threads=args.threads, fixed_dims=dims) for p in args.models
    }
    ops = list(dict.fromkeys(op for t in tables.values() for op in t))
    sys.stdout.write(
        "| operator | " + " | ".join(tables) + " |\n|---|" + "---|" * len(tables) + "\n"
    )
    for op in ops:
        cells = " | ".join(f"{t.get(op, 0.0):.2f}" for t in tables.values())
        sys.stdout.write(f"| {op} | {cells} |\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

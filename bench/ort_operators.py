"""Where onnxruntime's time goes: per-operator kernel times from its profiler, and MAC counts.

Used by ``bench/inference_speed.py`` (figures ``ops_<model>_<Op>_ms``, ``<model>_gmac_640x480``)
and on its own::

    python bench/ort_operators.py model.onnx [other.onnx ...] --threads 2
    python bench/ort_operators.py before.onnx after.onnx baseline.onnx --cpu-rounds 40

Kernel times are onnxruntime's own (``SessionOptions.enable_profiling``; events ``*_kernel_time``):
each node's median over the calls after the warm-up, summed per operator type. They
add up to less than the wall time (the executor's own work between the kernels is not in them),
and a loaded CPU inflates them as it does the wall time: compare operators within one run.

``--cpu-rounds`` also times the models' calls by the CPU time of the calling thread, one
intra-op thread, the models interleaved call by call (:func:`cpu_time_interleaved`): time the
thread spends descheduled does not count, so on a host shared with other jobs the ratios hold
where wall times swing by 2x from one round to the next.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import sys
import tempfile
import time
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
    """Kernel milliseconds per call of each operator type of the ONNX model at ``path``
    (:func:`operator_breakdowns` of one model)."""
    return operator_breakdowns(
        [path], threads=threads, fixed_dims=fixed_dims, calls=calls, warmup=warmup, seed=seed
    )[0]


def operator_breakdowns(
    paths: list[str | os.PathLike],
    *,
    threads: int,
    fixed_dims: Mapping[str, int] | None = None,
    calls: int = 8,
    warmup: int = 2,
    seed: int = 0,
) -> list[dict[str, float]]:
    """Kernel milliseconds per call of each operator type of each ONNX model: the sum over its
    nodes of each node's median over the calls. The models are called in turn, one call each per
    round, so that a slow phase of the host falls on all of them.

    Args:
        paths: ONNX files with one float input each.
        threads: onnxruntime intra-op threads.
        fixed_dims: symbolic input dimensions to fix (as ``OnnxModel(fixed_dims=...)``).
        calls: profiled calls after ``warmup`` unprofiled-in-the-figures ones.
        seed: the random input's.

    Returns:
        Per model, ``{op type: ms}``, largest first, plus ``"TOTAL"`` (the sum of the kernel
        times).
    """
    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmp:
        sessions = []
        for i, path in enumerate(paths):
            options = ort.SessionOptions()
            options.intra_op_num_threads = threads
            options.add_session_config_entry("session.force_spinning_stop", "1")
            for name, size in (fixed_dims or {}).items():
                options.add_free_dimension_override_by_name(name, int(size))
            options.enable_profiling = True
            options.profile_file_prefix = str(Path(tmp) / f"ort{i}")
            session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
            inp = session.get_inputs()[0]
            shape = [d if isinstance(d, int) else (fixed_dims or {}).get(d, 1) for d in inp.shape]
            x = np.random.default_rng(seed).standard_normal(shape).astype(np.float32)
            sessions.append((session, {inp.name: x}))
        for _ in range(warmup + calls):
            for session, feed in sessions:
                session.run(None, feed)
        profiles = [json.loads(Path(s.end_profiling()).read_text()) for s, _ in sessions]
    return [_per_operator(events, warmup) for events in profiles]


def _per_operator(events: list[dict], warmup: int) -> dict[str, float]:
    """``{op type: ms}`` from one session's profile (calls after ``warmup``), plus ``"TOTAL"``."""
    runs = sorted((e["ts"], e["ts"] + e["dur"]) for e in events if e.get("name") == "model_run")
    # each node's median over the calls: a kernel that lost its core mid-call (a shared host)
    # inflates one sample of one node, not the figure
    per_node: dict[str, list[float]] = collections.defaultdict(list)
    op_of: dict[str, str] = {}
    kernels = [e for e in events if e.get("cat") == "Node" and e["name"].endswith("_kernel_time")]
    for start, end in runs[warmup:]:
        for e in kernels:
            if start <= e["ts"] <= end:
                per_node[e["name"]].append(e["dur"] / 1000.0)
                op_of[e["name"]] = e["args"]["op_name"]
    medians: collections.Counter[str] = collections.Counter()
    for node, samples in per_node.items():
        medians[op_of[node]] += statistics.median(samples)
    medians["TOTAL"] = sum(medians.values())
    return dict(sorted(medians.items(), key=lambda kv: -kv[1]))


def cpu_time_interleaved(
    paths: list[str | os.PathLike],
    *,
    fixed_dims: Mapping[str, int] | None = None,
    rounds: int = 20,
    warmup: int = 2,
    seed: int = 0,
) -> list[list[float]]:
    """CPU milliseconds of the calling thread per call of each ONNX model, one intra-op thread.

    The models run in turn, one call each per round, on the same random input (one float input,
    symbolic dimensions from ``fixed_dims``, else 1). With one intra-op thread onnxruntime runs the
    whole call on the calling thread, so ``time.thread_time`` holds all of its work and none of
    the time the thread waits for a core.

    Returns:
        One list of ``rounds`` times per model, in the order of ``paths``.
    """
    import onnxruntime as ort

    sessions = []
    for path in paths:
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        for name, size in (fixed_dims or {}).items():
            options.add_free_dimension_override_by_name(name, int(size))
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        inp = session.get_inputs()[0]
        shape = [d if isinstance(d, int) else (fixed_dims or {}).get(d, 1) for d in inp.shape]
        x = np.random.default_rng(seed).standard_normal(shape).astype(np.float32)
        sessions.append((session, {inp.name: x}))
    for session, feed in sessions:
        for _ in range(warmup):
            session.run(None, feed)
    times: list[list[float]] = [[] for _ in sessions]
    for _ in range(rounds):
        for (session, feed), samples in zip(sessions, times):
            start = time.thread_time()
            session.run(None, feed)
            samples.append((time.thread_time() - start) * 1e3)
    return times


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
    parser.add_argument(
        "--cpu-rounds",
        type=int,
        default=0,
        help="also time each model's calls by thread CPU time, 1 thread, interleaved (rounds)",
    )
    args = parser.parse_args(argv)
    dims = {"batch": 1, "height": args.size[0], "width": args.size[1]}
    if args.cpu_rounds:
        times = cpu_time_interleaved(args.models, fixed_dims=dims, rounds=args.cpu_rounds)
        last = statistics.median(times[-1])
        sys.stdout.write(f"CPU ms per call, 1 thread, {args.cpu_rounds} interleaved rounds\n")
        sys.stdout.write(f"| model | median | min | median / {args.models[-1].stem} |\n")
        sys.stdout.write("|---|---:|---:|---:|\n")
        for path, samples in zip(args.models, times):
            med = statistics.median(samples)
            sys.stdout.write(
                f"| {path.stem} | {med:.1f} | {min(samples):.1f} | {med / last:.3f} |\n"
            )
    tables = dict(
        zip(
            (p.stem for p in args.models),
            operator_breakdowns(args.models, threads=args.threads, fixed_dims=dims, calls=12),
        )
    )
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

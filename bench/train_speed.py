"""Training-step speed of ENet and of the joint network (frozen trunk) on the CPU.

One training step = forward + loss + ``zero_grad`` + backward + Adam step, as in
``training.loop.train_one_epoch``:

- ``enet``: ENet (8 classes) at 320x240, batch 8, cross-entropy, Adam over every parameter;
- ``joint``: the joint network with ``freeze_trunk=True`` at 320x240, batch 8, MSE on the
  normals, Adam over the normals head only (the normals stage of the thesis).

Contenders are *runtime options* of the training process (the model code is the same), each run
in a fresh subprocess because OpenMP reads its environment at start-up:

- ``t2_default``: torch's default (2 intra-op threads on this 2-core box, libgomp's default
  wait policy, which busy-spins at every barrier) — what ``geoseg train`` does today;
- ``t2_passive``: 2 threads, ``OMP_WAIT_POLICY=PASSIVE`` (idle threads sleep instead of spin);
- ``t1``: ``torch.set_num_threads(1)``;
- ``t1_nofill``: 1 thread and ``torch.utils.deterministic.fill_uninitialized_memory = False``;
- ``t1_nofill_cl``: as ``t1_nofill``, model and input in ``torch.channels_last``.

Every contender runs with ``torch.use_deterministic_algorithms(True, warn_only=True)`` as the
trainer does by default (``deterministic: true``). In that mode torch also fills every fresh
``torch.empty`` tensor with NaN (``torch.utils.deterministic.fill_uninitialized_memory``, on by
default): ~3,500 ``aten::fill_`` calls per ENet step, 15-25 % of the step in the profile. Turning
the fill off keeps the deterministic kernels (and the results) unchanged.

Why: on a shared 2-core machine (other processes, or the trainer's own data-loader worker),
two spinning OpenMP threads get descheduled in turn and every one of the ~1,500 ops of a step
waits for its partner thread at a barrier; the step then costs several times the single-thread
step. The profile shows no pathological op in the model itself (see the docstring of
:mod:`geoseg.models.enet`).

The contenders run in interleaved rounds (one subprocess per contender per round, in a rotating
order), each timing a warm-up step and then ``--steps`` steps; the table reports the minimum over
all timed steps of all rounds (the best estimate of the uncontended cost on a loaded box) and the
median, with the ratio to ``t2_default``. The 1-minute load average before and after is recorded.

Usage::

    python bench/train_speed.py                  # ~10 min on a loaded 2-core box
    python bench/train_speed.py --rounds 1 --steps 2 --contenders t2_default t1

Prints a Markdown table and writes ``bench/results/train_speed.json`` (with ``machine`` and
``command``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import provenance  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "train_speed.json"
H, W, BATCH = 240, 320, 8

_PASSIVE = {"OMP_WAIT_POLICY": "PASSIVE"}
CONTENDERS: dict[str, dict] = {
    "t2_default": {"threads": None, "env": {}, "fill": True, "channels_last": False},
    "t2_passive": {"threads": None, "env": _PASSIVE, "fill": True, "channels_last": False},
    "t1": {"threads": 1, "env": {}, "fill": True, "channels_last": False},
    "t1_nofill": {"threads": 1, "env": {}, "fill": False, "channels_last": False},
    "t1_nofill_cl": {"threads": 1, "env": {}, "fill": False, "channels_last": True},
}
MODELS = ("enet", "joint")


def _child(spec: dict, steps: int, models: list[str]) -> dict[str, list[float]]:
    """Time ``steps`` training steps (after one warm-up) of each model; seconds per step."""
    import warnings

    import torch
    import torch.nn.functional as F

    from geoseg.models.enet import enet
    from geoseg.models.joint import joint

    warnings.filterwarnings("ignore")  # deterministic-mode warnings (max_unpool2d)
    if spec["threads"] is not None:
        torch.set_num_threads(spec["threads"])
    torch.use_deterministic_algorithms(True, warn_only=True)  # as training/ does by default
    # deterministic mode also fills every fresh torch.empty with NaN (~3,500 fills per step)
    torch.utils.deterministic.fill_uninitialized_memory = spec["fill"]
    fmt = torch.channels_last if spec["channels_last"] else torch.contiguous_format
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(BATCH, 3, H, W, generator=gen).contiguous(memory_format=fmt)
    labels = torch.randint(0, 8, (BATCH, H, W), generator=gen)
    target = F.normalize(torch.randn(BATCH, 3, H, W, generator=gen), dim=1)
    out: dict[str, list[float]] = {}
    for name in models:
        torch.manual_seed(0)
        if name == "enet":
            model = enet(num_classes=8)
        else:
            model = joint(num_classes=8, freeze_trunk=True)
        model = model.to(memory_format=fmt).train()
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.Adam(params, lr=5e-4, weight_decay=2e-4)

        times = []
        for i in range(steps + 1):
            t0 = time.perf_counter()
            outputs = model(x)
            if name == "enet":
                loss = F.cross_entropy(outputs["logits"], labels)
            else:
                loss = (outputs["normals"] - target).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if i > 0:  # the first step is the warm-up
                times.append(time.perf_counter() - t0)
        out[name] = times
    out["threads"] = [torch.get_num_threads()]
    return out


def _run_child(name: str, steps: int, models: list[str]) -> dict[str, list[float]]:
    spec = CONTENDERS[name]
    env = {**os.environ, **spec["env"]}
    cmd = [sys.executable, __file__, "--child", name, "--steps", str(steps), "--models", *models]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{name}: child failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--steps", type=int, default=2, help="timed steps per model per round")
    parser.add_argument("--contenders", nargs="+", default=list(CONTENDERS), choices=CONTENDERS)
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    parser.add_argument("--child", choices=CONTENDERS, help=argparse.SUPPRESS)
    parser.add_argument("--no-write", action="store_true", help="do not write the JSON")
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(_child(CONTENDERS[args.child], args.steps, args.models)))
        return {}

    import torch

    load_before = os.getloadavg()[0]
    meta = provenance(
        "random inputs and targets (torch seed 0): a speed measurement, no tuning or reporting "
        "data",
        command=" ".join(["python", "bench/train_speed.py", *(argv or sys.argv[1:])]),
    )
    times: dict[str, dict[str, list[float]]] = {c: {m: [] for m in args.models} for c in CONTENDERS}
    threads: dict[str, int] = {}
    contenders = list(args.contenders)
    for r in range(args.rounds):
        order = contenders[r % len(contenders) :] + contenders[: r % len(contenders)]
        for name in order:
            got = _run_child(name, args.steps, args.models)
            threads[name] = int(got.pop("threads")[0])
            for model, ts in got.items():
                times[name][model].extend(ts)
            print(f"round {r + 1}/{args.rounds} {name}: {got}", file=sys.stderr, flush=True)
    load_after = os.getloadavg()[0]

    results: dict = {
        "size_hw": [H, W],
        "batch": BATCH,
        "rounds": args.rounds,
        "steps_per_round": args.steps,
        "load_avg_1min_before": round(load_before, 2),
        "load_avg_1min_after": round(load_after, 2),
    }
    base = "t2_default" if "t2_default" in contenders else contenders[0]
    header = "| contender | threads | " + " | ".join(
        f"{m} min s | {m} median s | {m} speed-up (min)" for m in args.models
    )
    lines = [header + " |", "|" + "---|" * (2 + 3 * len(args.models))]
    for name in contenders:
        row = [name, str(threads[name])]
        for model in args.models:
            ts = times[name][model]
            best, med = min(ts), statistics.median(ts)
            speedup = min(times[base][model]) / best
            results[f"{name}_{model}_min_s"] = round(best, 4)
            results[f"{name}_{model}_median_s"] = round(med, 4)
            results[f"{name}_{model}_speedup_vs_{base}"] = round(speedup, 3)
            row += [f"{best:.3f}", f"{med:.3f}", f"{speedup:.2f}x"]
        results[f"{name}_threads"] = threads[name]
        lines.append("| " + " | ".join(row) + " |")
    table = "\n".join(lines)
    print(
        f"\nTraining step (fwd + bwd + Adam), {W}x{H}, batch {BATCH}; load {load_before:.1f} → "
        f"{load_after:.1f}\n\n{table}"
    )
    results.update(meta)
    results["machine"] += f", torch {torch.__version__}"
    if not args.no_write:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(results, indent=2) + "\n")
        print(f"\nwrote {RESULTS}")
    return results


if __name__ == "__main__":
    main()

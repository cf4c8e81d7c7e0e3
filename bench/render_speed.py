"""Render speed and occlusion benchmark of the synthetic world (geoseg.synth).

Measures, on this machine, with all channels (RGB, labels, normals, depth, instance ids):

- frames per second at 320x240 and 640x480 along a car drive through the default city
  (``configs/world_default.yaml``), wall clock and process CPU time (``time.process_time``: a
  busy shared machine inflates the wall clock), with the default renderer (cast shadows on)
  and without shadows; the embree ray cast's share of the frame time;
- the occlusion share in ``configs/world_dense_occlusion.yaml``: of the facade pixels visible
  when trees, vehicles and street furniture are dropped from the scene, the share hidden when
  they are present (car and tram drives, same poses).

Usage: ``python bench/render_speed.py [--frames N] [--full]``. Prints a Markdown table and writes
``bench/results/render_speed.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from geoseg.config import load_config
from geoseg.synth.renderer import Renderer
from geoseg.synth.trajectory import drive
from geoseg.synth.world import WorldConfig, build_world

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from provenance import provenance  # noqa: E402

OCCLUDERS = ("vegetation", "vehicle", "object")


def time_frames(renderer: Renderer, traj, n: int) -> dict[str, float]:
    """Render ``n`` frames (after one warm-up); wall and CPU frames/s, embree ms per frame."""
    renderer.render(traj.K, traj.R_wc[0], traj.t_wc[0], traj.image_size)
    index = np.linspace(0, len(traj) - 1, n).round().astype(int)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i in index:
        renderer.render(
            traj.K, traj.R_wc[i], traj.t_wc[i], traj.image_size, time_s=float(traj.timestamps[i])
        )
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    # the primary embree cast alone, same rays
    cast_cpu = 0.0
    for i in index:
        rays_c = renderer._camera_rays(traj.K, *traj.image_size)
        rays_w = (rays_c @ traj.R_wc[i].T.astype(np.float32)).astype(np.float32)
        start = time.process_time()
        renderer._static.cast(None, rays_w, traj.t_wc[i])
        cast_cpu += time.process_time() - start
    return {
        "fps_wall": n / wall,
        "fps_cpu": n / cpu,
        "ms_cpu": 1000 * cpu / n,
        "embree_ms_cpu": 1000 * cast_cpu / n,
    }


def occlusion_share(world: WorldConfig, length_m: float) -> dict[str, float]:
    full = Renderer(world)
    bare = Renderer(world, drop=OCCLUDERS)
    n_facades = len(world.facades())
    out = {}
    visible_all = hidden_all = 0
    for rig in ("car", "tram"):
        traj = drive(world, rig=rig, length_m=length_m, fps=1.0, seed=0)
        visible = hidden = 0
        for i in range(len(traj)):
            pose = (traj.K, traj.R_wc[i], traj.t_wc[i], traj.image_size)
            with_occ = full.render(*pose, time_s=float(traj.timestamps[i])).instance
            without = bare.render(*pose, time_s=float(traj.timestamps[i])).instance
            seen_bare = (without >= 0) & (without < n_facades)
            seen_full = (with_occ >= 0) & (with_occ < n_facades)
            visible += int(seen_bare.sum())
            hidden += int((seen_bare & ~seen_full).sum())
        out[f"dense_occlusion_facade_hidden_share_{rig}"] = hidden / max(visible, 1)
        visible_all += visible
        hidden_all += hidden
    out["dense_occlusion_facade_hidden_share"] = hidden_all / max(visible_all, 1)
    return out


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=60, help="frames timed at 320x240")
    parser.add_argument("--full", action="store_true", help="4x the frames and route length")
    args = parser.parse_args(argv)
    scale = 4 if args.full else 1
    n_small = args.frames * scale
    n_large = max(args.frames // 3, 5) * scale

    load_start = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    meta = provenance(
        "world_default (car route, seed 0) and world_dense_occlusion: a speed measurement, "
        "no tuning or reporting data",
        command=" ".join(["python", "bench/render_speed.py", *(argv or sys.argv[1:])]),
    )
    t0 = time.perf_counter()
    world = build_world(load_config(WorldConfig, ROOT / "configs" / "world_default.yaml"))
    build_s = time.perf_counter() - t0
    results: dict[str, float | str] = {"world_build_s": build_s}
    for shadows in (False, True):
        renderer = Renderer(world, shadows=shadows)  # the default renderer casts no shadows
        suffix = "_shadows" if shadows else ""
        for (w, h), n in (((320, 240), n_small), ((640, 480), n_large)):
            traj = drive(world, rig="car", length_m=300.0, fps=10.0, seed=0, image_size=(w, h))
            m = time_frames(renderer, traj, n)
            key = f"{w}x{h}{suffix}"
            results[f"fps_{key}"] = m["fps_wall"]
            results[f"fps_{key}_cpu"] = m["fps_cpu"]
            results[f"ms_{key}_cpu"] = m["ms_cpu"]
            results[f"embree_ms_{key}_cpu"] = m["embree_ms_cpu"]
    dense = build_world(load_config(WorldConfig, ROOT / "configs" / "world_dense_occlusion.yaml"))
    results.update(occlusion_share(dense, 400.0 * scale))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    results["load_average_1min_start"] = load_start
    results["load_average_1min_end"] = load
    results.update(meta)
    results["machine"] += (
        f", load {load:.1f} at the end (a shared machine: the *_cpu figures, from "
        "time.process_time, are the less disturbed ones)"
    )

    print("| figure | value |")
    print("|---|---|")
    for key, value in results.items():
        text = f"{value:.3f}" if isinstance(value, float) else str(value)
        print(f"| {key} | {text} |")
    out = ROOT / "bench" / "results" / "render_speed.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"\nwritten {out.relative_to(ROOT)}")
    return results


if __name__ == "__main__":
    main()

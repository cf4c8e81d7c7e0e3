"""``geoseg demo``: the end-to-end demonstration on the synthetic world.

Renders one short route with both rigs (car: forward camera; tram: side camera) under two
appearance conditions, writes a contact sheet of the four sequences and a top-down map of
the world with its GIS products (true buildings, the erroneous building model, DEM segments,
true trajectories, GPS fixes), segments the frames with the shipped network, then runs the
chapter-4 chain on a short occluded drive (the image SLAM with GPS + DEM, without building
constraints, with the ray-cast baseline's and with the network's), and prints where
everything is.

The demo is a list of steps (:data:`STEPS`), each a function of a shared :class:`DemoContext`
that records what it wrote in ``context.outputs``.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

DEFAULT_CONFIG = Path("configs/world_default.yaml")
RIGS = ("car", "tram")
#: the buildings step's building models, and what each run is given besides the images
DEMO_MODELS = {
    "exact": "true facades, odometry + DEM, no GPS",
    "gis": "GIS model with its errors, GPS + DEM + odometry",
}
DRIVE_M = 150.0  # the buildings step's drive: long enough to start and fuse, about a minute
MAX_DRIVE_M = 5000.0


@dataclass
class DemoContext:
    """State shared by the demo steps.

    Attributes:
        out: output directory.
        world_config: the world's configuration.
        rigs: camera rigs rendered.
        conditions: appearance conditions rendered.
        frames: frames per sequence.
        image_size: ``(W, H)``.
        fps: frame rate of the sequences (low by default: few frames, a long enough route
            for the map to show the GPS error).
        seed: seed of the routes and GIS errors.
        drive_m: length of the drive of the buildings step (0: no such step).
        force: redo steps whose outputs exist.
        overwrite: write into sequence folders that hold files no render wrote.
        world: the built world (set by the first step that needs it).
        sequences: ``(rig, condition)`` -> sequence directory.
        outputs: label -> path of what the steps wrote, printed at the end.
        figures: figure name -> value of what the steps measured, written to ``demo.json``
            (the README's demo figures are ``bench/demo.py``'s copy of it).
    """

    out: Path
    world_config: Any
    rigs: tuple[str, ...] = RIGS
    conditions: tuple[str, ...] = ("summer_day", "winter")
    frames: int = 10
    image_size: tuple[int, int] = (320, 240)
    fps: float = 1.0
    seed: int = 0
    drive_m: float = 0.0
    force: bool = False
    overwrite: bool = False
    world: Any = None
    sequences: dict[tuple[str, str], Path] = field(default_factory=dict)
    outputs: dict[str, Path] = field(default_factory=dict)
    figures: dict[str, float | int] = field(default_factory=dict)

    def get_world(self) -> Any:
        if self.world is None:
            from geoseg.synth.world import build_world

            self.world = build_world(self.world_config)
        return self.world


def step_render(ctx: DemoContext) -> None:
    """Render every (rig, condition) sequence with its GIS products."""
    from geoseg.synth.export import render_sequence

    world = ctx.get_world()
    for rig in ctx.rigs:
        for condition in ctx.conditions:
            ctx.sequences[(rig, condition)] = render_sequence(
                ctx.world_config,
                ctx.out / "sequences" / f"{rig}_{condition}",
                frames=ctx.frames,
                condition=condition,
                rig=rig,
                image_size=ctx.image_size,
                fps=ctx.fps,
                seed=ctx.seed,
                world=world,
                overwrite=ctx.force,
                allow_other_files=ctx.overwrite,
                progress=True,
            )
    ctx.outputs["sequences"] = ctx.out / "sequences"


def step_contact_sheet(ctx: DemoContext) -> None:
    """One row per sequence: a few RGB frames and the label map of the middle one."""
    import numpy as np

    from geoseg.legends import class_legend
    from geoseg.reloc.image_base import read_rgb
    from geoseg.synth.maps import contact_sheet

    rows, labels = [], []
    n_show = min(4, ctx.frames)
    picks = np.unique(np.linspace(0, ctx.frames - 1, n_show).round().astype(int))
    for (rig, condition), seq in ctx.sequences.items():
        row = [read_rgb(seq / "rgb" / f"{i:06d}.png") for i in picks]
        mid = picks[len(picks) // 2]
        row.append(read_rgb(seq / "labels_color" / f"{mid:06d}.png"))
        rows.append(row)
        labels.append(f"{rig} camera\n{condition}")
    rows.append([class_legend()])
    labels.append("class colours")
    path = contact_sheet(
        rows,
        ctx.out / "contact_sheet.png",
        row_labels=labels,
        col_labels=[f"RGB, frame {i}" for i in picks]
        + [f"true labels, frame {picks[len(picks) // 2]}"],
        title="rendered frames: each route with both rigs under two conditions (rows)",
    )
    ctx.outputs["contact sheet"] = path


def step_map(ctx: DemoContext) -> None:
    """Top-down map: true buildings, GIS building model, DEM, both trajectories, GPS."""
    from geoseg.synth.export import GisConfig, drive_frames, make_gis_products
    from geoseg.synth.maps import plot_map

    world = ctx.get_world()
    tracks, gps, products = {}, {}, None
    for rig in ctx.rigs:
        # the very drives step_render rendered (deterministic)
        traj = drive_frames(
            world, ctx.frames, rig=rig, fps=ctx.fps, seed=ctx.seed, image_size=ctx.image_size
        )
        products = make_gis_products(world, traj, GisConfig(), seed=ctx.seed)
        tracks[rig] = traj.vehicle_xyz[:, :2]
        gps[rig] = products.gps
    path = plot_map(
        ctx.out / "map.png",
        true_footprints=[b.footprint for b in world.buildings],
        building_model=products.building_model if products else None,
        dem=products.dem if products else None,
        streets=world.streets,
        tracks=tracks,
        gps=gps,
        # two lines: one would run past the left panel's edge
        title=f"world seed {ctx.world_config.seed} from above: true buildings, the GIS building "
        "model (with its errors),\nDEM road segments, the routes driven, GPS fixes",
    )
    ctx.outputs["map"] = path


def step_segment(ctx: DemoContext) -> None:
    """Run the shipped labels + normals network (onnxruntime) on every rendered frame.

    Scores it against the renderer's ground truth (the demo city is not the held-out evaluation
    city; ``bench/accuracy_seg.py`` measures that) and writes a thesis fig. 4.20-like sheet:
    RGB | true labels | predicted labels | predicted normals | true normals, one row per
    sequence. Skipped, with the command that trains them, when no weights are shipped.
    """
    import cv2
    import numpy as np
    import torch

    from geoseg.classes import CLASS_NAMES, NUM_CLASSES, SKY, colorize
    from geoseg.errors import GeosegError
    from geoseg.infer import normals_to_rgb
    from geoseg.legends import class_legend, normal_key
    from geoseg.pretrained import pretrained_segmenter
    from geoseg.reloc.image_base import read_rgb
    from geoseg.synth.maps import contact_sheet
    from training.metrics import confusion_matrix, segmentation_scores

    try:
        segmenter = pretrained_segmenter("normals", backend="onnx")
    except GeosegError as err:
        logger.warning("segment step skipped: %s", err)
        return
    cm = torch.zeros((NUM_CLASSES, NUM_CLASSES), dtype=torch.int64)
    rows, row_labels = [], []
    for (rig, condition), seq in ctx.sequences.items():
        mid = ctx.frames // 2
        for i in range(ctx.frames):
            rgb = read_rgb(seq / "rgb" / f"{i:06d}.png")
            truth = cv2.imread(str(seq / "labels" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
            if truth is None or truth.shape != rgb.shape[:2]:
                raise GeosegError(f"{seq / 'labels' / f'{i:06d}.png'}: missing or unreadable")
            result = segmenter(rgb)
            pred = result.labels[0].astype(np.int64)
            cm += confusion_matrix(torch.from_numpy(pred), torch.from_numpy(truth.astype(np.int64)))
            if i != mid:
                continue
            with np.load(seq / "geometry" / f"{i:06d}.npz") as geometry:
                true_normals = geometry["normals"].astype(np.float32)
            row = [rgb, colorize(truth), colorize(pred)]
            if result.normals is not None:  # no surface on predicted sky: grey, as the truth
                row.append(normals_to_rgb(np.where(pred == SKY, 0.0, result.normals[0])))
            row.append(normals_to_rgb(true_normals))
            rows.append(row)
            row_labels.append(f"{rig} / {condition}\nframe {i}")
    scores = segmentation_scores(cm)
    miou, accuracy = scores["miou"], scores["pixel_acc"]
    columns = ["RGB", "true labels", "predicted labels", "predicted normals", "true normals"]
    rows.append([class_legend(), normal_key()])
    row_labels.append("keys:\nclasses, normals")
    path = contact_sheet(
        rows,
        ctx.out / "segmentation.png",
        row_labels=row_labels,
        col_labels=columns if len(rows[0]) == 5 else columns[:3] + columns[4:],
        title=f"shipped labels + normals network on the demo frames (all frames: mIoU {miou:.2f}, "
        f"pixel accuracy {accuracy:.2f}); normals in the camera frame, grey = no surface (sky)",
    )
    per_class = ", ".join(
        f"{name} {scores[f'iou_{name}']:.2f}"
        for name in CLASS_NAMES
        if scores[f"iou_{name}"] == scores[f"iou_{name}"]  # NaN: class absent and not predicted
    )
    print(
        f"segmentation ({segmenter.source.name}, {ctx.frames * len(ctx.sequences)} frames): "
        f"mIoU {miou:.3f}, pixel accuracy {accuracy:.3f}; IoU {per_class}"
    )
    ctx.figures.update(segmentation_miou=miou, segmentation_pixel_accuracy=accuracy)
    ctx.outputs["segmentation"] = path


def step_buildings(ctx: DemoContext) -> None:
    """The whole chain of chapter 4 on a short drive through an occluded street
    (:mod:`slam_bridge.experiments.buildings_ch4`): the image SLAM without building constraints,
    with the ray-cast baseline's and with the joint network + eq. 4.14's, against two building
    models: ``exact`` (the true facades with odometry + DEM and no GPS, the thesis's synthetic
    run: without buildings the trajectory drifts, with them it stays on the facades) and
    ``gis`` (the erroneous GIS model with GPS + DEM + odometry, as a user runs it). Writes
    ``buildings/``: the report ``buildings_ch4.md``, the trajectories, the map points by
    association and the model reprojected into keyframes, per model."""
    import dataclasses

    from geoseg.config import default_config_file, load_config
    from slam_bridge.experiments.buildings_ch4 import BuildingsConfig, run_experiment

    if ctx.drive_m <= 0:
        return
    source = default_config_file("buildings_ch4.yaml")
    cfg = load_config(BuildingsConfig, source) if source else BuildingsConfig()
    cfg = dataclasses.replace(
        cfg.quick(), methods=["nobuild", "raycast", "bayes"], models=list(DEMO_MODELS),
        async_run=False,  # the worker's timings need the long drive: bench/buildings_ch4.py
        drive=dataclasses.replace(cfg.drive, length_m=ctx.drive_m),
    )  # fmt: skip
    out = run_experiment(cfg, ctx.out / "buildings", overwrite=ctx.overwrite, force=ctx.force)
    runs = json.loads((out / "buildings_ch4.json").read_text())["runs"]
    for model, setting in DEMO_MODELS.items():
        print(f"slam on images, {model} building model ({setting}):")
        for method in cfg.methods:
            print("  " + _run_line(method, runs[f"{method}_{model}"]))
            ctx.figures.update(_run_figures(f"{method}_{model}", runs[f"{method}_{model}"]))
    ctx.outputs["buildings report"] = out / "buildings_ch4.md"
    for picture in sorted(out.glob("*.png")):
        ctx.outputs[picture.stem.replace("_", " ")] = picture


def _run_line(method: str, r: dict) -> str:
    """One SLAM run of the buildings step, as the demo prints it."""
    from slam_bridge.experiments.buildings_ch4_plots import METHOD_NAMES

    name = f"{METHOD_NAMES.get(method, method)} ({method})"
    if "error" in r:
        return f"{name:38s}: failed ({r['error']})"
    gps = f" (GPS fixes {r['gps_error_m']:.2f} m)" if "gps_error_m" in r else ""
    line = (
        f"{name:38s}: {r['translation_error_m']:.3f} m, {r['rotation_error_deg']:.2f} deg "
        f"mean error{gps}"
    )
    if r.get("association_precision") is not None:
        line += (
            f"; {r['associated_points']} points on facades, "
            f"{100 * r['association_precision']:.0f} % on the right one"
        )
    return line


#: what the demo keeps of each SLAM run of the buildings step (``<name>_<method>_<model>``)
RUN_FIGURES = (
    "translation_error_m", "rotation_error_deg", "tracking_failures", "gps_error_m",
    "associated_points", "association_precision",
)  # fmt: skip


def _run_figures(run: str, r: dict) -> dict[str, float | int]:
    """The figures of one SLAM run of the buildings step, by ``<name>_<run>``."""
    return {f"{name}_{run}": r[name] for name in RUN_FIGURES if r.get(name) is not None}


# The demo, in order; later issues append (name, step) pairs.
STEPS: list[tuple[str, Callable[[DemoContext], None]]] = [
    ("render", step_render),
    ("contact sheet", step_contact_sheet),
    ("map", step_map),
    ("segment", step_segment),
    ("buildings", step_buildings),
]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out", type=Path, default=Path("geoseg_demo"), help="output directory (geoseg_demo/)"
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help=f"world config YAML (default: {DEFAULT_CONFIG} of the working directory, else of "
        "the geoseg source tree, else built-in defaults)",
    )
    parser.add_argument("--frames", type=int, default=10, help="frames per sequence (default 10)")
    parser.add_argument("--fps", type=float, default=1.0, help="frame rate (default 1)")
    parser.add_argument(
        "--size", default="320x240", help="image size WxH (default 320x240, the networks' size)"
    )
    parser.add_argument(
        "--conditions",
        default="summer_day,winter",
        help="two (or more) comma-separated conditions (default summer_day,winter)",
    )
    parser.add_argument("--seed", type=int, default=None, help="seed of the city, routes and GIS")
    parser.add_argument(
        "--drive-m", type=float, default=DRIVE_M,
        help=f"length of the occluded drive the SLAM and the network bridge run on (default "
        f"{DRIVE_M:g} m; 0: skip)",
    )  # fmt: skip
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a world config key (repeatable)",
    )  # fmt: skip
    parser.add_argument("--force", action="store_true", help="redo steps whose outputs exist")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="write into an --out folder that holds files the demo did not write (they are "
        "kept, unless a file of the same name is written)",
    )


def _earlier_demo(folder: Path) -> bool:
    """True when ``folder`` is a demo output written before output markers existed."""
    names = {p.name for p in folder.iterdir()}
    return {"sequences", "contact_sheet.png", "map.png"} <= names and names <= {
        "sequences",
        "contact_sheet.png",
        "map.png",
        "segmentation.png",
    }


def run(args: argparse.Namespace) -> int:
    from geoseg.config import default_config_file, load_config
    from geoseg.errors import GeosegError
    from geoseg.output_dir import prepare_output_dir
    from geoseg.synth.conditions import get_condition
    from geoseg.synth.export import check_fps, parse_size
    from geoseg.synth.world import WorldConfig

    start = time.perf_counter()
    size = parse_size(args.size)
    if args.frames < 1:
        raise GeosegError(f"--frames: expected an integer >= 1, got {args.frames}")
    if not 0 <= args.drive_m <= MAX_DRIVE_M:  # NaN fails too
        raise GeosegError(
            f"--drive-m: expected a length in [0, {MAX_DRIVE_M:g}] m, got {args.drive_m}"
        )
    check_fps(args.fps, "--fps")
    conditions = tuple(c.strip() for c in args.conditions.split(",") if c.strip())
    if len(conditions) < 2 or len(set(conditions)) != len(conditions):
        raise GeosegError(
            f"--conditions: expected two or more different comma-separated conditions (the "
            f"demo compares the same routes under them), got {args.conditions!r}"
        )
    for c in conditions:
        get_condition(c)
    out = prepare_output_dir(
        args.out, producer="demo", overwrite=args.overwrite, adopt=_earlier_demo
    )
    source = args.config
    if source is None:
        source = default_config_file(DEFAULT_CONFIG.name)
        if source is None:
            logger.warning("no %s found: using the built-in world defaults", DEFAULT_CONFIG)
    overrides = list(args.overrides) + ([f"seed={args.seed}"] if args.seed is not None else [])
    world_config = load_config(WorldConfig, source, overrides=overrides)
    ctx = DemoContext(
        out=out,
        world_config=world_config,
        conditions=conditions,
        frames=args.frames,
        image_size=size,
        fps=args.fps,
        seed=world_config.seed,
        drive_m=args.drive_m,
        force=args.force,
        overwrite=args.overwrite,
    )
    for name, step in STEPS:
        t0 = time.perf_counter()
        step(ctx)
        logger.info("demo step %s: %.1f s", name, time.perf_counter() - t0)
    if ctx.figures:
        ctx.outputs["figures"] = out / "demo.json"
        (out / "demo.json").write_text(json.dumps(ctx.figures, indent=1, sort_keys=True) + "\n")
    print(f"geoseg demo finished in {time.perf_counter() - start:.1f} s; outputs in {out}/")
    for label, path in ctx.outputs.items():
        print(f"  {label}: {path}")
    return 0

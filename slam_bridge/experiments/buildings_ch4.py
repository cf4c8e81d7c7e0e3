"""The chapter-4 experiment (thesis §4.2.4.2, §4.3.4): building constraints chosen by networks.

A drive with loops through a ``dense_occlusion`` city (trees, parked and moving vehicles,
poles and shelters in front of the facades) is rendered once, then run through the image SLAM
(:func:`slam_bridge.system.image_slam.run_on_images`, same front end for every run) with each way of
choosing building constraints (``methods``):

* ``nobuild``: no building constraint;
* ``raycast``: the chapter-2 baseline (a point whose ray from the camera hits the building
  model is a building point; nearest facade);
* ``dirichlet``: the naive CNN + the shipped Dirichlet filter (2015, ``D(P_Z) > t_D``);
* ``bayes``: the joint network (labels + normals) and eq. 4.14 (2016);
* ``oracle``: every map point on the facade it really lies on (the renderer's instance ids):
  the upper bound,

against two building models (``models``):

* ``exact``: the true facades, wheel odometry + the road DEM, no GPS; the first keyframes
  take their true poses (:class:`~slam_bridge.slam.loop.KnownStartPoses`), as the thesis's
  synthetic run starts from a known pose. Buildings constrain some axes, odometry and the DEM
  the rest (§4.2.4.2). Its k-BA window may be longer (``exact_window_keyframes``): with no GPS
  it is what remembers the facades that last crossed the street.
* ``gis``: the GIS model ``geoseg render`` writes (shifted and rotated footprints, missing and
  extra buildings) with a GPS of ``sigma_b = gps_sigma_m`` + the DEM + odometry, started as a
  user starts it (two views, georeferenced by the GPS; no ground truth).

Each run is evaluated against the truth (errors of the keyframes, tracking failures, the
association's precision and recall against :class:`~slam_bridge.experiments.facade_truth.
FacadeTruth`) and saved as it finishes (``runs/<method>_<model>.json`` + ``.npz``): an
interrupted experiment resumes where it stopped. :func:`run_experiment` writes the flat
figures (``buildings_ch4.json``), their tables (``buildings_ch4.md``) and the pictures
(:mod:`slam_bridge.experiments.buildings_ch4_plots`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slam_bridge.bridge.builder import BridgeConfig, build_bridge, check_covers_window
from slam_bridge.bridge.worker import BridgeWorker
from slam_bridge.errors import SlamError
from slam_bridge.experiments.buildings_ch4_plots import METHOD_NAMES
from slam_bridge.experiments.replay import RecordingConstraints, ReplayBridge
from slam_bridge.system.image_slam import ImageSlamConfig

logger = logging.getLogger(__name__)

__all__ = [
    "METHODS",
    "MODELS",
    "DriveConfig",
    "BuildingsConfig",
    "prepare_drive",
    "run_one",
    "run_experiment",
]

METHODS = ("nobuild", "raycast", "dirichlet", "bayes", "oracle")
MODELS = ("exact", "gis")


@dataclass
class DriveConfig:
    """The rendered drive.

    Attributes:
        preset: world preset (``dense_occlusion``: occluders everywhere).
        world_seed: the city.
        blocks: ``(x, y)`` blocks of the city; a small city makes a long route loop back.
        rig: ``car`` or ``tram``.
        condition: appearance condition.
        route_seed: the route.
        length_m: distance driven.
        fps: frame rate.
        image_size: ``(W, H)`` of the rendered images.
        world: the city's street geometry, fields of :class:`~geoseg.synth.world.WorldConfig`
            (:func:`~geoseg.synth.world_config.with_layout`; empty: the defaults).
    """

    preset: str = "dense_occlusion"
    world_seed: int = 7
    blocks: tuple[int, int] = (2, 2)
    rig: str = "car"
    condition: str = "summer_day"
    route_seed: int = 7
    length_m: float = 1200.0
    fps: float = 10.0
    image_size: tuple[int, int] = (640, 480)
    world: dict = field(default_factory=dict)

    def world_config(self):
        from geoseg.synth.world import WorldConfig
        from geoseg.synth.world_config import with_layout

        bx, by = self.blocks
        cfg = WorldConfig(seed=self.world_seed, preset=self.preset, blocks_x=bx, blocks_y=by)
        return with_layout(cfg, self.world)


def _default_slam() -> ImageSlamConfig:
    from geoseg.config import default_config_file, load_config

    source = default_config_file("slam_images.yaml")
    return load_config(ImageSlamConfig, source) if source else ImageSlamConfig()


@dataclass
class BuildingsConfig:
    """The chapter-4 experiment (``configs/buildings_ch4.yaml``).

    Attributes:
        drive: the rendered drive.
        bridge: the bridge's settings (its ``association`` is each method's; its
            ``window_weight`` is the GIS model's cap, whose errors must not outvote the GPS).
        exact_bridge: the bridge settings that differ with the exact model (``radius_m``: no
            model error to cover, only the map's own drift; ``window_weight``: None, no cap:
            the model is right, the more rows the better).
        exact_window_keyframes: the k-BA window's length ``l`` with the exact model (None:
            ``slam``'s). Without a GPS the window is what remembers the last facades that
            crossed the street's axis; the GIS model's runs keep ``slam``'s (its GPS anchors
            every keyframe).
        naive_infer_every: the naive CNN labels every this many keyframes (its dense
            prediction costs ~40x the joint network's on a CPU; a point is seen in several
            keyframes, so most still gather its evidence).
        async_run: one more run of ``bayes`` on the ``gis`` model (or the first model) with the
            worker asynchronous (``bayes_<model>_async``), for the timing figures; the others
            follow ``bridge.asynchronous`` (false in the config: deterministic figures that do
            not depend on the machine's load).
        timing_pairs: after the runs, this many pairs of ``nobuild`` and asynchronous
            ``bayes`` runs on the same model, one right after the other (``nobuild`` first in
            every other pair): ``async_time_ratio`` is the median of the pairs' ratios (0:
            from ``nobuild_<model>`` and the ``async_run``, measured far apart while the
            machine's load drifts).
        slam: the image SLAM (default: ``configs/slam_images.yaml``).
        methods: among :data:`METHODS`.
        models: among :data:`MODELS`.
        gps_sigma_m: the GPS of the ``gis`` model, ``N(0, sigma^2)`` per axis at every frame.
        gps_bias: the ``gis`` model's GPS is instead :func:`geoseg.synth.gps.simulate_gps`'s
            default error model at the frame rate (a locally constant bias of up to 3 m, noise,
            dropouts; ``gps_sigma_m`` unused), as ``bench/slam_images.py``'s ``bias`` log:
            the bench of a biased GPS (``bench/gps_bias.py``).
        start_keyframes: keyframes placed at their true poses (``exact`` model).
        quick_length_m: drive length of the default (non ``--full``) run.
        seed: seed of the GPS noise.
    """

    drive: DriveConfig = field(default_factory=DriveConfig)
    bridge: BridgeConfig = field(default_factory=BridgeConfig)
    exact_bridge: dict = field(default_factory=lambda: {"radius_m": 1.5, "window_weight": None})
    exact_window_keyframes: int | None = None
    naive_infer_every: int = 3
    async_run: bool = True
    timing_pairs: int = 3
    slam: ImageSlamConfig = field(default_factory=_default_slam)
    methods: list[str] = field(default_factory=lambda: list(METHODS))
    models: list[str] = field(default_factory=lambda: list(MODELS))
    gps_sigma_m: float = 0.75
    gps_bias: bool = False
    start_keyframes: int = 3
    quick_length_m: float = 250.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name, given, known in (
            ("methods", self.methods, METHODS),
            ("models", self.models, MODELS),
        ):
            if not given or set(given) - set(known):
                raise SlamError(f"{name}: expected some of {list(known)}, got {given}")
        if self.gps_sigma_m < 0:
            raise SlamError(f"gps_sigma_m: expected >= 0, got {self.gps_sigma_m}")
        if self.start_keyframes < 2:
            raise SlamError(f"start_keyframes: expected >= 2, got {self.start_keyframes}")
        try:
            exact_window = self.slam_for("exact").slam.window
        except SlamError as exc:  # e.g. shorter than the pose-graph cameras of a hybrid
            raise SlamError(f"exact_window_keyframes: {exc}") from None
        for window in (self.slam.slam.window, exact_window):  # recent_keyframes cover both
            check_covers_window(self.bridge, window)
        known = {f.name for f in dataclasses.fields(BridgeConfig)} - {"association"}
        if set(self.exact_bridge) - known:
            raise SlamError(
                f"exact_bridge: unknown keys {sorted(set(self.exact_bridge) - known)}; "
                f"expected some of {sorted(known)}"
            )
        if self.naive_infer_every < 1:
            raise SlamError(f"naive_infer_every: expected >= 1, got {self.naive_infer_every}")
        if self.timing_pairs < 0:
            raise SlamError(f"timing_pairs: expected >= 0, got {self.timing_pairs}")

    def slam_for(self, model: str) -> ImageSlamConfig:
        """The image SLAM's settings of the runs on ``model`` (``exact_window_keyframes``)."""
        if model != "exact" or self.exact_window_keyframes is None:
            return self.slam
        window = dataclasses.replace(self.slam.slam.window, l=self.exact_window_keyframes)
        loop = dataclasses.replace(self.slam.slam, window=window)
        return dataclasses.replace(self.slam, slam=loop)

    def timing_model(self) -> str:
        """The model of the asynchronous timing run."""
        return "gis" if "gis" in self.models else self.models[0]

    def quick(self) -> BuildingsConfig:
        """The default (short) run: the same city and route, ``quick_length_m`` long, without
        the timing pairs (a short drive times little)."""
        drive = dataclasses.replace(self.drive, length_m=self.quick_length_m)
        return dataclasses.replace(self, drive=drive, timing_pairs=0)


# ------------------------------------------------------------------------------- the drive
def prepare_drive(cfg: BuildingsConfig, folder: str | Path, workers: int | None = None) -> Path:
    """Render the drive into ``folder`` (skipped when it holds the same render) and write its
    GPS log (``gps_sigma<s>.csv``) and the exact building model (``gis/exact/``).

    Args:
        workers: rendering processes (default: one per CPU core, at most 4; a script of your
            own must guard its entry point, see :func:`geoseg.synth.export.render_sequence`).

    Returns:
        ``folder``.
    """
    from geoseg.synth.export import drive_frames, render_sequence
    from geoseg.synth.gps import GpsConfig, simulate_gps
    from geoseg.synth.world import build_world

    d = cfg.drive
    world_cfg = d.world_config()
    world = build_world(world_cfg)
    guess = int(d.length_m / 4.0 * d.fps)  # frames at 4 m/s, grown until the route is long enough
    while True:
        traj = drive_frames(
            world, guess, rig=d.rig, fps=d.fps, seed=d.route_seed, image_size=d.image_size
        )
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(traj.t_wc, axis=0), axis=1))]
        if arc[-1] >= d.length_m:
            frames = int(np.searchsorted(arc, d.length_m)) + 1
            break
        guess = int(guess * 1.5)
    folder = render_sequence(
        world_cfg, folder, frames=frames, condition=d.condition, rig=d.rig,
        image_size=d.image_size, fps=d.fps, seed=d.route_seed, world=world,
        allow_other_files=True, workers=workers or min(4, os.cpu_count() or 1),
    )  # fmt: skip
    from slam_bridge.csv_columns import read_columns

    poses = read_columns(folder / "poses.csv", ["timestamp", "vehicle_x", "vehicle_y", "vehicle_z"])
    antenna = np.column_stack([poses["vehicle_x"], poses["vehicle_y"], poses["vehicle_z"]])
    if cfg.gps_bias:  # the simulator's default receiver: a bias that GPS fusion cannot remove
        gps = GpsConfig(rate_hz=d.fps)
    else:
        gps = GpsConfig(
            rate_hz=d.fps, bias_max_m=0.0, bias_std_m=0.0, noise_std_m=cfg.gps_sigma_m,
            dropout_share=0.0,
        )  # fmt: skip
    simulate_gps(poses["timestamp"], antenna, gps, seed=cfg.seed).write_csv(_gps_path(cfg, folder))
    _write_exact_model(world, folder / "gis" / "exact")
    return folder


def _gps_path(cfg: BuildingsConfig, folder: Path) -> Path:
    if cfg.gps_bias:
        return folder / f"gps_bias_seed{cfg.seed}.csv"
    return folder / f"gps_sigma{cfg.gps_sigma_m:g}.csv"


def _write_exact_model(world, directory: Path) -> None:
    """The true buildings as a GIS model without errors (``facades.csv``, ``buildings_model.ply``,
    the layout of the render's ``gis/``; every facade its own truth)."""
    from geoseg.synth.buildings import BuildingErrorConfig, build_building_model

    exact = BuildingErrorConfig(
        max_horizontal_error_m=0.0, horizontal_error_std_m=0.0, max_rotation_deg=0.0,
        height_error="scale", height_scale_range=(1.0, 1.0), min_height_m=1e-3,
        missing_share=0.0, extra_count=0,
    )  # fmt: skip
    directory.mkdir(parents=True, exist_ok=True)
    build_building_model(world.buildings, exact).write(directory)


# ------------------------------------------------------------------------------- one run
@dataclass
class RunAssets:
    """What the runs of one drive share (read once)."""

    folder: Path
    image_size: tuple[int, int]
    facades: dict  # model -> Facades
    meshes: dict  # model -> trimesh.Trimesh
    world: object = None  # the true facades (the exact model), for the evaluation


def load_assets(cfg: BuildingsConfig, folder: Path) -> RunAssets:
    """The building models (each run's bridge loads the shipped network itself: in a child
    process when it is asynchronous)."""
    import trimesh

    from slam_bridge.bridge.facades import Facades

    facades, meshes = {}, {}
    for model in cfg.models:
        gis = folder / "gis" / ("exact" if model == "exact" else "")
        facades[model] = Facades.read_csv(gis / "facades.csv")
        meshes[model] = trimesh.load(gis / "buildings_model.ply", force="mesh")
    assets = RunAssets(folder, tuple(cfg.drive.image_size), facades, meshes)
    assets.world = Facades.read_csv(folder / "gis" / "exact" / "facades.csv")
    return assets


def _worker(
    cfg: BuildingsConfig, assets: RunAssets, method: str, model: str, truth, asynchronous: bool
):
    """The bridge of ``method`` against ``model`` (None for ``nobuild``)."""
    from geoseg.classes import NUM_CLASSES
    from slam_bridge.bridge.constraints import BuildingConstraints

    if method == "nobuild":
        return None
    facades = assets.facades[model]
    settings = _settings(cfg, method, model, asynchronous)
    if method != "oracle":
        return build_bridge(
            settings, facades,
            image_size=assets.image_size, mesh=assets.meshes[model],
        )  # fmt: skip
    # the oracle: the truth gathered beside the SLAM, keyframe by keyframe
    constraints = BuildingConstraints(
        facades, sigma_m=settings.sigma_m, window_weight=settings.window_weight
    )
    return _OracleWorker(
        truth, None, NUM_CLASSES, lambda s: truth.oracle(facades, s.points, settings.radius_m),
        constraints, associate_every=settings.associate_every,
        asynchronous=settings.asynchronous,
    )  # fmt: skip


def _settings(cfg: BuildingsConfig, method: str, model: str, asynchronous: bool) -> BridgeConfig:
    """The bridge settings of one run."""
    settings = dataclasses.replace(
        cfg.bridge, asynchronous=asynchronous,
        association=method if method in ("raycast", "dirichlet", "bayes") else "bayes",
    )  # fmt: skip
    if model == "exact":
        settings = dataclasses.replace(settings, **cfg.exact_bridge)
    if method == "dirichlet":
        settings = dataclasses.replace(settings, infer_every=cfg.naive_infer_every)
    return settings


def _signature(cfg: BuildingsConfig, method: str, model: str, asynchronous: bool) -> str:
    """Everything a run's figures depend on: a saved run is reused only when it matches."""
    from geoseg.config import to_dict

    parts = {
        "method": method, "model": model,
        "drive": {k: v for k, v in to_dict(cfg.drive).items() if v or k != "world"},
        "slam": {  # its own `bridge` is not this experiment's; no bridge, no GPS bias estimate
            k: v
            for k, v in to_dict(cfg.slam_for(model)).items()
            if k != "bridge" and not (k == "gps_bias" and method == "nobuild")
        },
        "gps_sigma_m": cfg.gps_sigma_m, "start_keyframes": cfg.start_keyframes,
        "seed": cfg.seed,
    }  # fmt: skip
    if cfg.gps_bias:  # absent otherwise: the saved runs of the unbiased GPS stay valid
        parts["gps_bias"] = True
    if method != "nobuild":
        parts["bridge"] = to_dict(_settings(cfg, method, model, asynchronous))
        if not asynchronous:  # inline: where an asynchronous worker would run changes nothing
            parts["bridge"].pop("worker", None)
    return json.dumps(parts, sort_keys=True, default=str)


class _OracleWorker(BridgeWorker):
    """A bridge whose association is the truth: it gathers each keyframe's votes first."""

    def __init__(self, truth, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.truth = truth

    def __call__(self, slam_map, k, obs) -> None:
        self.truth.observe(slam_map, k)
        super().__call__(slam_map, k, obs)


def run_one(
    cfg: BuildingsConfig,
    assets: RunAssets,
    method: str,
    model: str,
    asynchronous: bool,
    *,
    record: bool = False,
    replay: RecordingConstraints | None = None,
) -> tuple[dict, dict]:
    """One (method, model) run, its bridge asynchronous or not.

    Args:
        record: record the associations the fusion used (``arrays["recorded"]``, a
            :class:`~slam_bridge.experiments.replay.RecordingConstraints`).
        replay: give the fusion these recorded associations instead of running ``method``'s
            bridge (:class:`~slam_bridge.experiments.replay.ReplayBridge`: no worker).

    Returns:
        ``(figures, arrays)``: the figures (errors, tracking failures, association precision
        and recall, timings) and the arrays the pictures need (keyframe poses and timestamps,
        map points, their association and true facade).
    """
    from slam_bridge.experiments.facade_truth import FacadeTruth
    from slam_bridge.experiments.occluded_ch4 import point_classes
    from slam_bridge.slam.loop import KnownStartPoses
    from slam_bridge.system.image_slam import evaluate_run, load_inputs, run_on_images

    folder = assets.folder
    inputs = load_inputs(
        folder,
        gps=_gps_path(cfg, folder) if model == "gis" else None,
        odometry=folder / "gis" / "odometry.csv",
        dem=folder / "gis" / "dem.csv",
    )
    slam = cfg.slam_for(model)
    start = None
    if model == "exact":  # a known first pose (evaluation truth used for the start only)
        _, R_true, t_true = inputs.truth
        start = KnownStartPoses(
            R_true, t_true, slam.slam.tracking.outlier_gate_px, cfg.start_keyframes,
            slam.slam.mapping,
        )  # fmt: skip
    truth = FacadeTruth(folder, inputs.frames.timestamps)
    if replay is not None:
        worker = ReplayBridge(replay)
    else:
        worker = _worker(cfg, assets, method, model, truth, asynchronous)
    if record:  # the worker updates, and the fusion reads, the recording copy
        worker.constraints = RecordingConstraints(worker.constraints)
    t0 = time.perf_counter()
    result, _ = run_on_images(inputs, slam, progress=False, bridge=worker, start=start)
    wall = time.perf_counter() - t0
    m = result.map
    figures = {"method": method, "model": model, "asynchronous": asynchronous}
    figures["keyframes"] = m.num_keyframes
    figures.update(evaluate_run(result, inputs))
    figures["tracking_failures"] = int(result.tracking_failures)
    lost = [r.keyframe for r in result.records if r.tracking == "lost"]
    figures["first_lost_keyframe"] = lost[0] if lost else None
    figures["wall_seconds"] = wall
    figures["loop_ms_per_keyframe"] = 1e3 * float(np.mean([r.seconds for r in result.records]))
    figures["building_keyframes"] = sum("building" in r.constraints for r in result.records)
    if replay is not None:  # a timing run: nothing of its own to evaluate
        return figures, {}
    # the truth of every point, from all its observations (the oracle's own votes included)
    _, R_true, t_true = inputs.truth
    evaluation = FacadeTruth(folder, inputs.frames.timestamps, (R_true, t_true, m.K))
    evaluation.observe_all(m)
    rows = evaluation.model_rows(assets.facades[model], m.num_points)
    facade = np.full(m.num_points, -1, np.int64)
    right = np.zeros(m.num_points, dtype=bool)
    true_class = point_classes(folder, m, inputs.frames.timestamps)  # where the errors come from
    if worker is not None and worker.constraints.association is not None:
        a = worker.constraints.association.facade
        facade[: a.size] = a[: m.num_points]
        right = (facade >= 0) & (
            (facade == rows) | evaluation.lies_on(assets.world, facade, assets.facades[model])
        )
        figures.update(_association_figures(facade, rows, right, m.triangulated))
        figures.update(_worker_figures(worker, m.num_keyframes))
    e_h = _horizontal_errors(result, inputs)
    arrays = dict(
        timestamps=m.timestamps, t_wc=m.t_wc, R_wc=m.R_wc, K=m.K, in_world=result.in_world,
        error_m=e_h, points=np.where(m.triangulated[:, None], m.X_w, np.nan), facade=facade,
        right=right, true_facade=rows, true_points=evaluation.true_positions(m.num_points),
        true_class=true_class,
    )  # fmt: skip
    if record:
        arrays["recorded"] = worker.constraints
    return figures, arrays


def _association_figures(
    facade: np.ndarray, truth: np.ndarray, right: np.ndarray, triangulated: np.ndarray
) -> dict:
    """Precision: associated points on a facade they really lie on (``right``: the facade their
    pixels show, or one their true position lies on, as at a corner); recall: triangulated
    points on a facade of the model that are associated with one they lie on. Beside them, the
    precision by the pixels' facade alone (``association_precision_pixels``)."""
    got = (facade >= 0) & triangulated
    real = (truth >= 0) & triangulated
    share = lambda mask, of: float(np.mean(mask[of])) if of.any() else None  # noqa: E731
    return {
        "associated_points": int(got.sum()),
        "facade_points": int(real.sum()),
        "association_precision": share(right, got),
        "association_recall": share(right, real),
        "association_precision_pixels": share(facade == truth, got),
    }


def _worker_figures(worker, keyframes: int) -> dict:
    s = worker.stats
    out = {
        "association_ms_per_keyframe": 1e3 * sum(s.association_seconds) / max(keyframes, 1),
        "association_ms_per_run": 1e3 * float(np.mean(s.association_seconds)),
        "hook_ms_per_keyframe": 1e3 * float(np.mean(s.main_seconds)),
        "inference_dropped": s.dropped,
    }
    if s.inference_seconds:
        out["inference_ms_per_keyframe"] = 1e3 * float(np.mean(s.inference_seconds))
    if s.lags:
        out["constraint_lag_keyframes_median"] = float(np.median(s.lags))
        out["constraint_lag_keyframes_max"] = int(max(s.lags))
    return out


def _horizontal_errors(result, inputs) -> np.ndarray:
    """``(C,)`` each keyframe's horizontal error (NaN outside the world frame)."""
    t_true, _, T_true = inputs.truth
    m = result.map
    idx = np.clip(np.searchsorted(t_true, m.timestamps), 0, t_true.size - 1)
    e = np.linalg.norm(m.t_wc[:, :2] - T_true[idx, :2], axis=1)
    return np.where(result.in_world, e, np.nan)


# ------------------------------------------------------------------------------- the stage
def run_experiment(
    cfg: BuildingsConfig,
    out_dir: str | Path,
    *,
    data_dir: str | Path | None = None,
    force: bool = False,
    overwrite: bool = False,
) -> Path:
    """Every (method, model) run, the flat figures, tables and pictures (module docstring).

    Args:
        cfg: the experiment.
        out_dir: output directory (refused when it holds other files, unless ``overwrite``).
        data_dir: where the drive is rendered (default: ``out_dir/drive``; a rendering of the
            same request there is reused).
        force: rerun the runs already saved (a saved run whose settings differ from
            ``cfg``'s is rerun anyway).
        overwrite: write into a folder holding files this stage did not write.

    Returns:
        ``out_dir`` with ``buildings_ch4.json``, ``buildings_ch4.md``, ``runs/`` and the
        pictures.
    """
    from geoseg.config import to_dict
    from geoseg.output_dir import prepare_output_dir
    from slam_bridge.experiments import buildings_ch4_plots as plots

    out = prepare_output_dir(
        out_dir,
        producer="slam-eval buildings",
        overwrite=overwrite,
        adopt=lambda d: (d / "runs").is_dir() and (d / "config.json").is_file(),
    )
    runs_dir = out / "runs"
    runs_dir.mkdir(exist_ok=True)
    (out / "config.json").write_text(json.dumps(to_dict(cfg), sort_keys=True, default=str))
    t0 = time.perf_counter()
    folder = prepare_drive(cfg, Path(data_dir) if data_dir else out / "drive")
    assets = load_assets(cfg, folder)
    figures: dict[str, dict] = {}  # run name -> figures
    for method, model, asynchronous, name in _plan(cfg):
        saved = runs_dir / f"{name}.json"
        signature = _signature(cfg, method, model, asynchronous)
        if saved.is_file() and not force:
            earlier = json.loads(saved.read_text())
            if earlier.get("config") == signature:  # the same run: reused
                figures[name] = earlier
                continue
        try:
            fig, arrays = run_one(cfg, assets, method, model, asynchronous)
        except SlamError as exc:  # one failed run does not sink the others: reported
            logger.error("%s failed: %s", name, exc)
            fig, arrays = {"method": method, "model": model, "error": str(exc)}, None
        if arrays is not None:
            np.savez_compressed(runs_dir / f"{name}.npz", **arrays)
        fig["config"] = signature
        saved.write_text(json.dumps(fig, indent=1))
        figures[name] = fig
        logger.info("%s: %s", name, _short(fig))
    pairs = _timing_pairs(cfg, assets, runs_dir / "timing_pairs.json", force)
    summary = summarize(cfg, figures, pairs)
    summary["drive_length_m"] = _drive_length(folder)
    summary["wall_seconds"] = time.perf_counter() - t0
    (out / "buildings_ch4.json").write_text(json.dumps(summary, indent=1, sort_keys=True))
    (out / "buildings_ch4.md").write_text(markdown(cfg, summary))
    plots.write_pictures(out, folder, assets.facades, cfg.methods, cfg.models)
    return out


def _plan(cfg: BuildingsConfig) -> list[tuple[str, str, bool, str]]:
    """``(method, model, asynchronous, run name)`` of every run, the timing run last."""
    plan = [
        (method, model, cfg.bridge.asynchronous, f"{method}_{model}")
        for model in cfg.models
        for method in cfg.methods
    ]
    if cfg.async_run and "bayes" in cfg.methods:
        plan.append(("bayes", cfg.timing_model(), True, f"bayes_{cfg.timing_model()}_async"))
    return plan


def _timing_pairs(cfg: BuildingsConfig, assets, saved: Path, force: bool) -> list[dict]:
    """``cfg.timing_pairs`` pairs of runs on the timing model, ``nobuild`` and ``bayes`` with
    the worker asynchronous: main-loop milliseconds per keyframe of each, side by side; and
    right after the asynchronous run its building rows replayed without its worker
    (:mod:`~slam_bridge.experiments.replay`), which parts the ratio into the rows' cost and the
    worker's. ``nobuild`` runs first in even pairs and last in odd ones: a host whose speed
    drifts during a pass (a shared machine) then biases neither side. Saved in ``saved``,
    reused like the runs."""
    if cfg.timing_pairs == 0 or "bayes" not in cfg.methods:
        return []
    model = cfg.timing_model()
    signature = json.dumps(
        [_signature(cfg, "nobuild", model, False), _signature(cfg, "bayes", model, True)]
        + [cfg.timing_pairs, "replay", "alternating"]
    )
    if saved.is_file() and not force:
        earlier = json.loads(saved.read_text())
        if earlier.get("config") == signature:
            return earlier["pairs"]
    pairs = []
    for i in range(cfg.timing_pairs):
        nobuild_first = i % 2 == 0
        try:
            if nobuild_first:
                off, _ = run_one(cfg, assets, "nobuild", model, False)
            on, arrays = run_one(cfg, assets, "bayes", model, True, record=True)
            rows, _ = run_one(cfg, assets, "bayes", model, False, replay=arrays["recorded"])
            if not nobuild_first:
                off, _ = run_one(cfg, assets, "nobuild", model, False)
        except SlamError as exc:
            logger.error("timing pair %d failed: %s", i, exc)
            continue
        off_ms, on_ms = off["loop_ms_per_keyframe"], on["loop_ms_per_keyframe"]
        rows_ms = rows["loop_ms_per_keyframe"]
        pairs.append({
            "nobuild_ms": off_ms, "async_ms": on_ms, "ratio": on_ms / off_ms,
            "nobuild_first": nobuild_first,
            "replay_ms": rows_ms, "worker_ratio": on_ms / rows_ms, "rows_ratio": rows_ms / off_ms,
            "replay_error_difference_m": abs(
                rows["translation_error_m"] - on["translation_error_m"]
            ),
        })  # fmt: skip
        logger.info(
            "timing pair %d: %.1f / %.1f ms per keyframe (the rows without the worker: %.1f)",
            i, on_ms, off_ms, rows_ms,
        )  # fmt: skip
    saved.write_text(json.dumps({"config": signature, "pairs": pairs}, indent=1))
    return pairs


def summarize(
    cfg: BuildingsConfig, figures: dict[str, dict], pairs: list[dict] | None = None
) -> dict:
    """The flat keys of ``buildings_ch4.json`` (module docstring of ``bench/buildings_ch4.py``)
    and every run's figures under ``runs``; ``pairs``: the timing pairs
    (:func:`_timing_pairs`), which give ``async_time_ratio`` when there are any."""
    out: dict = {"runs": figures}
    primary = "exact" if "exact" in cfg.models else "gis"
    for method, model, _, name in _plan(cfg):
        f = figures.get(name, {})
        if name.endswith("_async"):
            continue
        for key in ("translation_error_m", "rotation_error_deg", "tracking_failures"):
            if key in f:
                out[f"{key}_{method}_{model}"] = f[key]
        # precision and recall against the exact model, where a facade's identity is the truth's
        for key in ("association_precision", "association_recall"):
            if f.get(key) is not None:
                out[f"{key}_{method}" if model == primary else f"{key}_{method}_{model}"] = f[key]
    timing = cfg.timing_model()
    bayes = figures.get(f"bayes_{timing}", {})
    on, off = figures.get(f"bayes_{timing}_async", {}), figures.get(f"nobuild_{timing}", {})
    for key in ("inference_ms_per_keyframe", "association_ms_per_keyframe"):
        # the worker as a user runs it (asynchronous) where there is such a run
        if key in on or key in bayes:
            out[key] = on.get(key, bayes.get(key))
    for key in ("constraint_lag_keyframes_median", "constraint_lag_keyframes_max"):
        if key in on:
            out[key] = on[key]
    if pairs:  # main-loop time per keyframe with the asynchronous worker on / off, same drive
        out["async_time_ratio"] = float(np.median([p["ratio"] for p in pairs]))
        out["async_time_ratios"] = [p["ratio"] for p in pairs]
        if all("worker_ratio" in p for p in pairs):  # the same rows with the worker / without
            out["async_time_ratio_same_rows"] = float(np.median([p["worker_ratio"] for p in pairs]))
            out["building_rows_time_ratio"] = float(np.median([p["rows_ratio"] for p in pairs]))
        out["timing_pairs"] = pairs
    elif "loop_ms_per_keyframe" in on and "loop_ms_per_keyframe" in off:
        out["async_time_ratio"] = on["loop_ms_per_keyframe"] / off["loop_ms_per_keyframe"]
    if "loop_ms_per_keyframe" in bayes and "loop_ms_per_keyframe" in off:
        out["sync_time_ratio"] = bayes["loop_ms_per_keyframe"] / off["loop_ms_per_keyframe"]
    return out


def _short(f: dict) -> str:
    keys = ("translation_error_m", "rotation_error_deg", "tracking_failures",
            "association_precision", "association_recall", "error")  # fmt: skip
    return ", ".join(
        f"{k}={f[k]:.3f}" if isinstance(f[k], float) else f"{k}={f[k]}"
        for k in keys
        if f.get(k) is not None
    )


def _drive_length(folder: Path) -> float:
    from slam_bridge.csv_columns import read_columns

    p = read_columns(folder / "poses.csv", ["vehicle_x", "vehicle_y"])
    xy = np.column_stack([p["vehicle_x"], p["vehicle_y"]])
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())


THESIS = {"exact": "1.3 cm, ~0.05 rad with the 2015 naive CNN + Dirichlet filter (§4.2), 1.2 km"}
MODEL_NOTES = {
    "exact": "The true facades, wheel odometry and the DEM, no GPS: the buildings are the only "
    "horizontal reference to the map, so `nobuild` drifts (the k-BA window: "
    "`exact_window_keyframes`).",
    "gis": "The GIS building model with its errors (shifted and rotated footprints, missing and "
    "extra buildings), a GPS, the DEM and odometry: the buildings refine a GPS trajectory, "
    "and the model's own errors bound how much (on a short drive the methods can sit within "
    "a few centimetres of `nobuild`, either side).",
}


#: the report's figures below its tables, in words
FIGURE_NOTES = {
    "inference_ms_per_keyframe": "network time per labelled keyframe, ms",
    "association_ms_per_keyframe": "association time (map points to facades) per keyframe, ms",
    "async_time_ratio": "SLAM loop time per keyframe with the network in its asynchronous "
    "worker, over the loop without buildings (1: the buildings cost nothing)",
    "sync_time_ratio": "SLAM loop time per keyframe with the network run inside the loop "
    "(synchronous: each labelled keyframe waits for it), over the loop without buildings",
    "constraint_lag_keyframes_median": "keyframes between a keyframe and the arrival of its "
    "building constraints, median",
    "constraint_lag_keyframes_max": "the same, largest",
}


def markdown(cfg: BuildingsConfig, summary: dict) -> str:
    """The tables: per model, a row per method."""
    lines = [
        f"# Building constraints (thesis chapter 4): {summary.get('drive_length_m', 0):.0f} m "
        f"drive, {cfg.drive.preset} city",
        "",
    ]
    for model in cfg.models:
        lines += [
            f"## Model `{model}`" + (f" (thesis: {THESIS[model]})" if model in THESIS else ""),
            "",
            *([MODEL_NOTES[model], ""] if model in MODEL_NOTES else []),
            "| method | translation error (m) | rotation error (deg) | tracking failures "
            "| associated points | precision | recall |",
            "|---|---|---|---|---|---|---|",
        ]
        for method in cfg.methods:
            f = summary["runs"].get(f"{method}_{model}", {})
            if "error" in f:
                lines.append(f"| {method} | failed: {f['error']} ||||||")
                continue
            cells = [
                _cell(f.get("translation_error_m"), 3),
                _cell(f.get("rotation_error_deg"), 3),
                str(f.get("tracking_failures", "")),
                str(f.get("associated_points", "")),
                _cell(f.get("association_precision"), 3),
                _cell(f.get("association_recall"), 3),
            ]
            name = METHOD_NAMES.get(method, method)
            lines.append(f"| {name}, `{method}` | " + " | ".join(cells) + " |")
        lines.append("")
    for key, note in FIGURE_NOTES.items():
        if key in summary:
            lines.append(f"- {note}: {_cell(summary[key], 3)} (`{key}`)")
    return "\n".join(lines) + "\n"


def _cell(v, digits: int) -> str:
    return "" if v is None else f"{v:.{digits}f}" if isinstance(v, float) else str(v)

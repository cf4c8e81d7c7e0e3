"""The chapter-3 fusion experiment (thesis §3.7, Tables 3.1-3.3, fig. 3.7) as a stage.

A drive through the synthetic city, keyframes every ``keyframe_spacing_m`` of the true path, and
one of two observation sources (``tracks``): landmarks sampled on the scene and observed with
pixel noise and gross outliers (``simulated``, as the thesis's synthetic sequence;
``configs/slam_ch3.yaml``), or the visual front end on the drive's rendered images (``images``:
the frames are rendered once into ``out_dir/frames``; the front end is given the true distance
driven, so that it places its keyframes as the simulated setup does). The first keyframes take
their true poses
(:class:`slam_bridge.slam.loop.KnownStartPoses`: the thesis evaluates the fusion on a SLAM
already expressed in the GPS's frame); every (method, GPS setting) pair runs the SLAM loop and
is evaluated against the truth. :func:`run_experiment` follows the stage contract (config in,
directory out, skipped when the directory already holds the results of the same config).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slam_bridge.errors import SlamError
from slam_bridge.experiments.landmarks import LandmarkConfig, Observations
from slam_bridge.experiments.simulated_tracks import SimulatedTracks
from slam_bridge.frontend.image_tracks import ImageTracks, ImageTracksConfig
from slam_bridge.slam.config import SlamConfig
from slam_bridge.slam.fusion import GpsConstraints
from slam_bridge.slam.loop import KnownStartPoses, SlamResult, run_slam
from slam_bridge.slam.windows import METHODS

logger = logging.getLogger(__name__)

__all__ = [
    "SequenceConfig",
    "ExperimentConfig",
    "Sequence",
    "make_sequence",
    "gps_for_setting",
    "run_method",
    "run_experiment",
]


@dataclass
class SequenceConfig:
    """The synthetic drive.

    Attributes:
        rig: ``car`` or ``tram``.
        length_m: distance driven (the thesis's synthetic sequence: 640 m).
        speed_mps: cruise speed (None: the rig's default).
        fps: frame rate of the drive.
        seed: route seed.
        image_size: ``(W, H)``.
        keyframe_spacing_m: a keyframe every this many metres driven.
    """

    rig: str = "car"
    length_m: float = 640.0
    speed_mps: float | None = None
    fps: float = 10.0
    seed: int = 0
    image_size: tuple[int, int] = (640, 480)
    keyframe_spacing_m: float = 2.0


def _default_world():
    from geoseg.synth.world import WorldConfig

    return WorldConfig()


@dataclass
class ExperimentConfig:
    """The chapter-3 experiment (``configs/slam_ch3.yaml``).

    Attributes:
        world: :class:`geoseg.synth.WorldConfig`.
        sequence: the drive.
        landmarks: points and measurement model (``tracks: simulated``).
        tracks: ``simulated`` (landmark projections) or ``images`` (the visual front end on
            rendered frames).
        condition: appearance condition of the rendered frames (``tracks: images``).
        frontend: the visual front end (``tracks: images``).
        slam: the keyframe loop (thesis: ``l = 40``, ``n = 30``).
        start_keyframes: first keyframes placed at their true poses and held fixed.
        methods: among ``ba``, ``dpc``, ``mpc``.
        gps_sigmas: sigma_b values (m) of the thesis's noise-only GPS (Table 3.1).
        gps_bias: add a run with :func:`geoseg.synth.gps.simulate_gps`'s locally constant bias,
            noise and dropouts (``gps`` settings).
        gps: the bias model of that run (``rate_hz`` is replaced by the frame rate).
        quick_length_m: sequence length of the default (non ``--full``) run.
        quick_sigmas: sigma_b values of the default run.
        quick_bias: whether the default run includes the bias setting.
        seed: seed of landmarks, noise and GPS.
    """

    world: object = field(default_factory=_default_world)
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    landmarks: LandmarkConfig = field(default_factory=LandmarkConfig)
    tracks: str = "simulated"
    condition: str = "summer_day"
    frontend: ImageTracksConfig = field(default_factory=ImageTracksConfig)
    slam: SlamConfig = field(default_factory=SlamConfig)
    start_keyframes: int = 3
    methods: list[str] = field(default_factory=lambda: ["ba", "dpc", "mpc"])
    gps_sigmas: list[float] = field(default_factory=lambda: [0.0, 0.75, 1.5])
    gps_bias: bool = True
    gps: object = None
    quick_length_m: float = 160.0
    quick_sigmas: list[float] = field(default_factory=lambda: [0.75])
    quick_bias: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        from geoseg.config import from_dict
        from geoseg.synth.gps import GpsConfig
        from geoseg.synth.world import WorldConfig

        if isinstance(self.world, dict):
            self.world = from_dict(WorldConfig, self.world, where="world")
        if self.gps is None:
            self.gps = GpsConfig()
        elif isinstance(self.gps, dict):
            self.gps = from_dict(GpsConfig, self.gps, where="gps")
        unknown = sorted(set(self.methods) - set(METHODS))
        if unknown or not self.methods:
            raise SlamError(f"methods: expected some of {sorted(METHODS)}, got {self.methods}")
        if any(s < 0 for s in self.gps_sigmas):
            raise SlamError(f"gps_sigmas: expected values >= 0, got {self.gps_sigmas}")
        if self.tracks not in ("simulated", "images"):
            raise SlamError(f"tracks: expected 'simulated' or 'images', got {self.tracks!r}")
        if self.start_keyframes < 2:
            raise SlamError(f"start_keyframes: expected >= 2, got {self.start_keyframes}")

    def quick(self) -> ExperimentConfig:
        """The default (short) run: ``quick_length_m`` and the quick GPS settings."""
        seq = dataclasses.replace(self.sequence, length_m=self.quick_length_m)
        return dataclasses.replace(
            self, sequence=seq, gps_sigmas=list(self.quick_sigmas), gps_bias=self.quick_bias
        )

    def settings(self) -> list[str]:
        """GPS setting names: ``sigma=0.75`` ... and ``bias``."""
        out = [f"sigma={s:g}" for s in self.gps_sigmas]
        return out + (["bias"] if self.gps_bias else [])


@dataclass
class Sequence:
    """A prepared sequence: keyframe observations, the truth (evaluation only) and its scene.

    Attributes:
        K: ``(3, 3)`` intrinsics.
        image_size: ``(W, H)``.
        timestamps: ``(C,)`` keyframe times, seconds.
        R_wc_true: ``(C, 3, 3)`` true keyframe rotations.
        t_wc_true: ``(C, 3)`` true optical centres.
        observations: the keyframe observations (sorted by keyframe).
        num_points: number of landmarks.
        frames: ``(C,)`` trajectory frame index of each keyframe.
        trajectory: the full :class:`geoseg.synth.Trajectory`.
        num_outliers: gross outliers planted.
    """

    K: np.ndarray
    image_size: tuple[int, int]
    timestamps: np.ndarray
    R_wc_true: np.ndarray
    t_wc_true: np.ndarray
    observations: Observations
    num_points: int
    frames: np.ndarray
    trajectory: object
    num_outliers: int

    @property
    def num_keyframes(self) -> int:
        """``C``."""
        return int(self.timestamps.size)

    def source(self) -> SimulatedTracks:
        """A fresh observation source over the keyframes."""
        o = self.observations
        return SimulatedTracks(self.K, self.image_size, self.timestamps, o.keyframe, o.point, o.uv)


def make_sequence(cfg: ExperimentConfig) -> Sequence:
    """World, drive, keyframes, landmarks and observations of the experiment (the simulated
    tracks; :func:`render_frames` and :func:`image_source` give the images')."""
    from geoseg.synth import build_world, drive
    from slam_bridge.experiments.landmarks import (
        SceneCaster,
        sample_landmarks,
        simulate_observations,
        visible_observations,
    )

    world = build_world(cfg.world)
    s = cfg.sequence
    traj = drive(
        world,
        rig=s.rig,
        length_m=s.length_m,
        speed_mps=s.speed_mps,
        fps=s.fps,
        seed=s.seed,
        image_size=tuple(s.image_size),
    )
    step = np.linalg.norm(np.diff(traj.t_wc, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(step)])
    targets = np.arange(0.0, arc[-1] + 1e-9, s.keyframe_spacing_m)
    frames = np.unique(np.searchsorted(arc, targets))
    frames = frames[frames < len(traj)]
    lm = sample_landmarks(world, traj.t_wc[:, :2], cfg.landmarks, seed=cfg.seed)
    caster = SceneCaster.from_world(world)
    kf, pt, uv_true = visible_observations(
        caster, lm, traj.K, traj.R_wc[frames], traj.t_wc[frames], traj.image_size, cfg.landmarks
    )
    obs = simulate_observations(kf, pt, uv_true, traj.image_size, cfg.landmarks, seed=cfg.seed)
    C = frames.size
    logger.info(
        "sequence: %.0f m, %d keyframes, %d landmarks, %d observations (%.0f per keyframe, "
        "%d outliers)",
        arc[-1], C, len(lm), len(obs), len(obs) / max(C, 1), int(obs.is_outlier.sum()),
    )  # fmt: skip
    return Sequence(
        K=traj.K,
        image_size=traj.image_size,
        timestamps=traj.timestamps[frames],
        R_wc_true=traj.R_wc[frames],
        t_wc_true=traj.t_wc[frames],
        observations=obs,
        num_points=len(lm),
        frames=frames,
        trajectory=traj,
        num_outliers=int(obs.is_outlier.sum()),
    )


def gps_for_setting(
    cfg: ExperimentConfig, seq: Sequence, setting: str, *, per_frame: bool = False
) -> np.ndarray:
    """GPS fixes of every keyframe (or every frame, ``per_frame``) for one setting.

    ``sigma=s``: the thesis's model for its synthetic sequence (§3.7.1.1): the true camera
    position plus ``N(0, s^2)`` per axis, no bias, no dropout. ``bias``: the locally constant
    bias + noise + dropouts of :func:`geoseg.synth.gps.simulate_gps` (``cfg.gps``), sampled at
    the frame rate so that every frame, hence every keyframe, has its fix (or a dropout).

    Returns:
        ``(C, 2)`` fixes (``(T, 2)`` with ``per_frame``), NaN for dropouts.
    """
    from geoseg.synth.gps import GpsConfig, simulate_gps

    traj = seq.trajectory
    if setting == "bias":
        gcfg = dataclasses.replace(cfg.gps, rate_hz=cfg.sequence.fps)
    elif setting.startswith("sigma="):
        sigma = float(setting.split("=", 1)[1])
        gcfg = GpsConfig(
            rate_hz=cfg.sequence.fps,
            bias_max_m=0.0,
            bias_std_m=0.0,
            noise_std_m=sigma,
            dropout_share=0.0,
        )
    else:
        raise SlamError(f"GPS setting: expected 'sigma=<m>' or 'bias', got {setting!r}")
    log = simulate_gps(traj.timestamps, traj.t_wc, gcfg, seed=cfg.seed + 17)
    frames = np.arange(len(traj)) if per_frame else seq.frames
    idx = np.clip(
        np.round((traj.timestamps[frames] - log.timestamps[0]) * gcfg.rate_hz), 0, len(log) - 1
    )
    return log.xy[idx.astype(np.int64)].copy()


def render_frames(cfg: ExperimentConfig, seq: Sequence, folder: Path):
    """Render every frame of the drive into ``folder`` (PNG, ``camera.json``,
    ``timestamps.csv``; the images are reused when already there) and open it.

    Returns:
        A :class:`slam_bridge.frontend.frames.ImageFolder`.
    """
    import cv2
    from tqdm import tqdm

    from geoseg.synth import build_world, render
    from slam_bridge.frontend.frames import ImageFolder

    traj = seq.trajectory
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{i:06d}.png" for i in range(len(traj))]
    if not all((folder / n).is_file() for n in names):
        world = build_world(cfg.world)
        for i in tqdm(range(len(traj)), desc="render", unit="frame"):
            frame = render(
                world, traj.K, traj.R_wc[i], traj.t_wc[i], traj.image_size, cfg.condition,
                time_s=float(traj.timestamps[i]),
            )  # fmt: skip
            cv2.imwrite(str(folder / names[i]), np.ascontiguousarray(frame.rgb[..., ::-1]))
    camera = {"K": np.asarray(traj.K).tolist(), "image_size": list(traj.image_size)}
    (folder / "camera.json").write_text(json.dumps(camera))
    rows = "".join(f"{n},{t:.6f}\n" for n, t in zip(names, traj.timestamps))
    (folder / "timestamps.csv").write_text("image,timestamp\n" + rows)
    return ImageFolder(folder)


def image_source(cfg: ExperimentConfig, seq: Sequence, frames) -> ImageTracks:
    """The visual front end on the rendered frames, spaced by the true distance driven."""
    traj = seq.trajectory
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(traj.t_wc, axis=0), axis=1))])

    def distance(t0: float, t1: float) -> float:
        return float(np.interp(t1, traj.timestamps, arc) - np.interp(t0, traj.timestamps, arc))

    keyframes = dataclasses.replace(
        cfg.frontend.keyframes, spacing_m=cfg.sequence.keyframe_spacing_m
    )
    return ImageTracks(
        frames, dataclasses.replace(cfg.frontend, keyframes=keyframes), distance=distance
    )


def run_method(
    cfg: ExperimentConfig,
    seq: Sequence,
    method: str,
    gps_xy: np.ndarray | None,
    *,
    frames=None,
    max_keyframes: int | None = None,
) -> SlamResult:
    """One SLAM run of the experiment: the true start poses, the GPS fixes of every keyframe
    (None: vision only); simulated tracks, or the front end on ``frames`` (then ``gps_xy``
    holds a fix per frame: :func:`gps_for_setting` with ``per_frame``)."""
    gate, A = cfg.slam.tracking.outlier_gate_px, cfg.start_keyframes
    if frames is None:
        source, times = seq.source(), seq.timestamps
        start = KnownStartPoses(seq.R_wc_true, seq.t_wc_true, gate, A, cfg.slam.mapping)
    else:
        traj = seq.trajectory
        source, times = image_source(cfg, seq, frames), traj.timestamps
        start = KnownStartPoses(traj.R_wc, traj.t_wc, gate, A, cfg.slam.mapping)
    providers = [] if gps_xy is None else [GpsConstraints(times, gps_xy)]
    return run_slam(source, method, start, providers, cfg.slam, max_keyframes=max_keyframes)


def keyframe_truth(seq: Sequence, result: SlamResult) -> tuple[np.ndarray, np.ndarray]:
    """``(R_wc (C, 3, 3), t_wc (C, 3))``: the true poses of the run's keyframes."""
    traj = seq.trajectory
    idx = np.searchsorted(traj.timestamps, result.map.timestamps)
    return traj.R_wc[idx], traj.t_wc[idx]


def run_experiment(
    cfg: ExperimentConfig, out_dir: str | Path, *, force: bool = False, overwrite: bool = False
) -> Path:
    """Run every (method, GPS setting) and write the tables, JSON and plots (a stage).

    Args:
        cfg: the experiment.
        out_dir: output directory (created; refused when it holds other files, unless
            ``overwrite``).
        force: rerun even when ``out_dir`` holds results of the same config.
        overwrite: write into a folder holding files this stage did not write.

    Returns:
        ``out_dir``, holding ``fusion_ch3.md``, ``fusion_ch3.json``, ``trajectory.png``,
        ``memory.png``, ``config.json`` and ``runs/<method>_<setting>.npz`` (per-keyframe
        final and online poses, ground truth, GPS, Hessian bytes, fusion timings, fallbacks).
    """
    from geoseg.config import to_dict
    from geoseg.output_dir import prepare_output_dir
    from slam_bridge.evaluation import tables_ch3 as ev

    out = prepare_output_dir(
        out_dir,
        producer="slam-eval fusion",
        overwrite=overwrite,
        adopt=lambda d: (d / "fusion_ch3.json").is_file() and (d / "config.json").is_file(),
    )
    cfg_json = json.dumps(to_dict(cfg), sort_keys=True, default=str)
    done = out / "fusion_ch3.json"
    if not force and done.is_file() and (out / "config.json").is_file():
        if (out / "config.json").read_text() == cfg_json:
            logger.info("%s already holds the results of this config; skipped", out)
            return out
    t0 = time.perf_counter()
    seq = make_sequence(cfg)
    frames = render_frames(cfg, seq, out / "frames") if cfg.tracks == "images" else None
    (out / "runs").mkdir(exist_ok=True)
    runs: list[ev.RunSummary] = []
    results: dict[tuple[str, str], SlamResult] = {}
    gps_of: dict[str, np.ndarray] = {}
    failures: list[dict] = []
    for setting in cfg.settings():
        gps_xy = gps_for_setting(cfg, seq, setting, per_frame=frames is not None)
        gps_of[setting] = gps_xy
        for method in cfg.methods:
            try:
                res = run_method(cfg, seq, method, gps_xy, frames=frames)
            except SlamError as exc:  # one failed run does not sink the grid: reported
                logger.error("%s / %s failed: %s", method, setting, exc)
                failures.append({"method": method, "setting": setting, "error": str(exc)})
                continue
            results[(method, setting)] = res
            R_true, t_true = keyframe_truth(seq, res)
            recs = ev.loop_records(res)
            np.savez_compressed(
                out / "runs" / f"{method}_{setting.replace('=', '')}.npz",
                R_wc=res.map.R_wc,
                t_wc=res.map.t_wc,
                R_wc_online=res.map.R_wc_online,
                t_wc_online=res.map.t_wc_online,
                t_wc_true=t_true,
                R_wc_true=R_true,
                gps_xy=gps_xy,
                hessian_bytes=np.array([r.hessian_bytes for r in recs]),
                fusion_seconds_per_iteration=np.array(
                    [r.fusion_seconds_per_iteration for r in recs]
                ),
                fusion_iterations=np.array([r.fusion_iterations for r in recs]),
                fallback=np.array([r.fallback for r in recs]),
            )
            runs.append(ev.summarize_run(res, R_true, t_true, setting))
            if frames is not None:  # the front end's tracks differ from run to run: no churn
                runs[-1].inlier_points = None
            logger.info("%s / %s: %s", method, setting, runs[-1].short())
    if not runs:
        raise SlamError(f"every run failed: {failures}")
    summary = ev.build_summary(runs, cfg.methods, cfg.settings())
    summary["failures"] = failures
    summary["sequence_length_m"] = float(
        np.sum(np.linalg.norm(np.diff(seq.t_wc_true, axis=0), axis=1))
    )
    summary["tracks"] = cfg.tracks
    if frames is None:
        summary["keyframes"] = seq.num_keyframes
        summary["observations"] = len(seq.observations)
        summary["outliers_planted"] = seq.num_outliers
    else:
        any_run = next(iter(results.values()))
        summary["keyframes"] = any_run.map.num_keyframes
        summary["observations"] = any_run.map.num_observations
    summary["wall_seconds"] = time.perf_counter() - t0
    ev.write_json(summary, done)
    ev.write_markdown(summary, out / "fusion_ch3.md")
    first = cfg.settings()[-1]
    ev.plot_trajectories(
        out / "trajectory.png",
        seq.trajectory.t_wc if frames is not None else seq.t_wc_true,
        {m: results[(m, first)].map.t_wc for m in cfg.methods if (m, first) in results},
        gps_of[first],
        title=f"trajectory vs GPS ({first}) vs ground truth",
    )
    ev.plot_memory(
        out / "memory.png",
        {
            m: np.array([r.hessian_bytes for r in ev.loop_records(results[(m, first)])])
            for m in cfg.methods
            if (m, first) in results
        },
    )
    (out / "config.json").write_text(cfg_json)
    return out

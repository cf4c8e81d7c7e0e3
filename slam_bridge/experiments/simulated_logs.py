"""Sensor logs simulated from a ground-truth trajectory: test the SLAM on a dataset that has
poses but no GPS (``geoseg slam simulate-logs``).

From camera poses (a KITTI ``poses.txt``, or a ``poses.csv``) it writes, in one folder:

* ``gps.csv``: fixes at ``gps_rate_hz`` (thesis eq. 1.84: a locally constant bias of up to
  ``gps_bias_max_m``, white noise of ``gps_sigma_m`` per axis, optional dropouts), with the true
  antenna position beside each fix (``true_x, true_y, true_z``: evaluation only);
* ``odometry.csv``: ``timestamp, speed_mps, yaw_rate_radps`` at the frame times: the speed with
  a relative noise of ``speed_noise_rel``, the yaw rate with ``yaw_rate_noise_radps``;
* ``dem.csv``: road segments every ``dem_step_m`` along the route, the road's altitude (the
  camera's minus ``camera_height_m``) with ``dem_noise_m`` of error at every vertex;
* ``truth.csv``: the true poses in the world frame (the columns of a render's ``poses.csv``),
  for ``geoseg slam run --truth``;
* ``frame.json``: how the world frame was made from the poses' frame, and every setting.

World frame. A KITTI pose is in the first camera's frame (x right, y down, z forward). The world
is metric, right-handed, z up: ``x_east = x_cam0``, ``y_north = z_cam0``, ``z_up = -y_cam0``,
then ``offset_m`` is added (for example UTM coordinates, to test world-sized numbers). A
``poses.csv`` (world frame already, z up) is only offset.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from geoseg.errors import check_finite, check_shape
from slam_bridge.errors import SlamError

__all__ = [
    "SimulatedLogsConfig",
    "KITTI_TO_WORLD",
    "simulate_logs",
    "write_truth_csv",
]

#: rotation of the z-up world frame from a KITTI first camera's frame (x right, y down, z forward)
KITTI_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass
class SimulatedLogsConfig:
    """How the logs are simulated (module docstring).

    Attributes:
        gps_rate_hz: fix rate.
        gps_sigma_m: white noise per horizontal axis, metres.
        gps_bias_max_m: bound of the locally constant bias (0: no bias).
        gps_bias_std_m: per-axis standard deviation of each bias value.
        gps_bias_hold_s: mean time a bias value holds.
        gps_dropout_share: long-run share of missing fixes.
        speed_noise_rel: relative standard deviation of a wheel-speed sample.
        yaw_rate_noise_radps: standard deviation of a yaw-rate sample, rad/s.
        dem_step_m: length of a DEM segment along the route.
        dem_noise_m: standard deviation of a DEM vertex's altitude error.
        camera_height_m: the camera's height above the road.
        offset_m: ``(3,)`` added to every world position.
        seed: random seed (the same seed gives the same logs).
    """

    gps_rate_hz: float = 1.0
    gps_sigma_m: float = 0.75
    gps_bias_max_m: float = 0.0
    gps_bias_std_m: float = 1.5
    gps_bias_hold_s: float = 30.0
    gps_dropout_share: float = 0.0
    speed_noise_rel: float = 0.01
    yaw_rate_noise_radps: float = 0.005
    dem_step_m: float = 5.0
    dem_noise_m: float = 0.2
    camera_height_m: float = 1.65
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("gps_rate_hz", "dem_step_m", "camera_height_m", "gps_bias_hold_s"):
            if not getattr(self, name) > 0:
                raise SlamError(f"{name}: expected > 0, got {getattr(self, name)}")
        for name in (
            "gps_sigma_m", "gps_bias_max_m", "gps_bias_std_m", "speed_noise_rel",
            "yaw_rate_noise_radps", "dem_noise_m",
        ):  # fmt: skip
            if not getattr(self, name) >= 0:
                raise SlamError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if not 0 <= self.gps_dropout_share < 1:
            raise SlamError(f"gps_dropout_share: expected [0, 1), got {self.gps_dropout_share}")
        offset = np.asarray(self.offset_m, dtype=np.float64)
        if offset.shape != (3,) or not np.isfinite(offset).all():
            raise SlamError(f"offset_m: expected 3 finite numbers, got {self.offset_m!r}")
        self.offset_m = tuple(float(v) for v in offset)


def headings(R_wc: np.ndarray) -> np.ndarray:
    """Heading of each camera's optical axis in the world's horizontal plane.

    Args:
        R_wc: ``(T, 3, 3)`` camera-to-world rotations (world z up, OpenCV camera).

    Returns:
        ``(T,)`` radians counter-clockwise from x (east), unwrapped.
    """
    forward = R_wc[:, :, 2]  # the camera's z axis in the world
    return np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))


def simulate_logs(
    timestamps: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    out_dir: str | Path,
    config: SimulatedLogsConfig | None = None,
    *,
    source: str = "",
    source_to_world: np.ndarray | None = None,
) -> Path:
    """Write the logs of a trajectory (module docstring).

    Args:
        timestamps: ``(T,)`` frame times, seconds, increasing.
        R_wc: ``(T, 3, 3)`` camera-to-world rotations in the poses' own frame.
        t_wc: ``(T, 3)`` optical centres in the poses' own frame.
        out_dir: the folder to write (created).
        config: the noise model.
        source: a name for the poses, recorded in ``frame.json``.
        source_to_world: ``(3, 3)`` rotation from the poses' frame to the z-up world frame
            (:data:`KITTI_TO_WORLD` for KITTI; None: the poses are z-up already).

    Returns:
        ``out_dir``.

    Raises:
        SlamError: shapes, non-finite poses, times that do not increase, fewer than 2 poses.
    """
    from geoseg.synth.gps import GpsConfig, simulate_gps

    cfg = config or SimulatedLogsConfig()
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    R_src = np.asarray(R_wc, dtype=np.float64)
    T_src = np.asarray(t_wc, dtype=np.float64)
    check_shape("R_wc", R_src, (t.size, 3, 3))
    check_shape("t_wc", T_src, (t.size, 3))
    for name, a in (("timestamps", t), ("R_wc", R_src), ("t_wc", T_src)):
        check_finite(name, a)
    if t.size < 2 or np.any(np.diff(t) <= 0):
        raise SlamError("timestamps: expected at least two increasing times")
    M = np.eye(3) if source_to_world is None else np.asarray(source_to_world, dtype=np.float64)
    offset = np.asarray(cfg.offset_m)
    R_w = M @ R_src
    T_w = T_src @ M.T + offset
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([int(cfg.seed), 0x10C5])

    gps_cfg = GpsConfig(
        rate_hz=cfg.gps_rate_hz,
        bias_max_m=cfg.gps_bias_max_m,
        bias_std_m=cfg.gps_bias_std_m if cfg.gps_bias_max_m > 0 else 0.0,
        bias_hold_s=cfg.gps_bias_hold_s,
        noise_std_m=cfg.gps_sigma_m,
        dropout_share=cfg.gps_dropout_share,
        altitude_error_std_m=0.0,
    )
    # world-sized offsets: the fixes are written in metres, the WGS84 columns are left out
    gps = simulate_gps(t, T_w, gps_cfg, seed=cfg.seed)
    table = np.column_stack(
        [gps.timestamps, gps.valid.astype(float), gps.xy, gps.true_xyz, gps.bias]
    )
    _write_csv(
        out / "gps.csv",
        "timestamp,valid,x,y,true_x,true_y,true_z,bias_x,bias_y",
        table,
        ["%.6f", "%d"] + ["%.4f"] * 7,
    )

    speed = _speeds(t, T_w)
    yaw = headings(R_w)
    yaw_rate = np.gradient(yaw, t)
    speed_meas = np.maximum(speed * (1.0 + cfg.speed_noise_rel * rng.standard_normal(t.size)), 0)
    yaw_meas = yaw_rate + cfg.yaw_rate_noise_radps * rng.standard_normal(t.size)
    _write_csv(
        out / "odometry.csv",
        "timestamp,speed_mps,yaw_rate_radps,true_speed_mps,true_yaw_rate_radps",
        np.column_stack([t, speed_meas, yaw_meas, speed, yaw_rate]),
        ["%.6f", "%.5f", "%.6f", "%.5f", "%.6f"],
    )

    vertices = _route_vertices(T_w, cfg.dem_step_m)
    z_road = (
        vertices[:, 2]
        - cfg.camera_height_m
        + cfg.dem_noise_m * rng.standard_normal(vertices.shape[0])
    )
    seg = np.column_stack([vertices[:-1, :2], z_road[:-1], vertices[1:, :2], z_road[1:]])
    _write_csv(out / "dem.csv", "x0,y0,z0,x1,y1,z1", seg, ["%.4f"] * 6)

    write_truth_csv(out / "truth.csv", t, R_w, T_w)
    meta = {
        "source": source,
        "source_to_world": M.tolist(),
        "offset_m": list(cfg.offset_m),
        "convention": (
            "X_world = source_to_world @ X_source + offset_m; world: metric, right-handed, z up "
            "(x east, y north); for KITTI: x_east = x_cam0, y_north = z_cam0, z_up = -y_cam0"
        ),
        "settings": asdict(cfg),
        "files": ["gps.csv", "odometry.csv", "dem.csv", "truth.csv"],
        "gps_error_m_mean": float(np.nanmean(np.linalg.norm(gps.xy - gps.true_xyz[:, :2], axis=1))),
    }
    (out / "frame.json").write_text(json.dumps(meta, indent=2) + "\n")
    return out


def write_truth_csv(path: Path, t: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray) -> Path:
    """True poses as a render's ``poses.csv``: ``frame, timestamp, tx, ty, tz, r00 ... r22``
    (``R_wc`` row-major), world metres (``%.6f``: millimetres stay exact at UTM sizes)."""
    names = ["frame", "timestamp", "tx", "ty", "tz"] + [
        f"r{i}{j}" for i in range(3) for j in range(3)
    ]
    table = np.column_stack([np.arange(t.size), t, t_wc, R_wc.reshape(-1, 9)])
    return _write_csv(path, ",".join(names), table, ["%d", "%.6f"] + ["%.6f"] * 3 + ["%.9f"] * 9)


def _write_csv(path: Path, header: str, table: np.ndarray, fmt: list[str]) -> Path:
    tmp = path.with_suffix(path.suffix + ".tmp")
    np.savetxt(tmp, table, fmt=fmt, delimiter=",", header=header, comments="")
    tmp.replace(path)
    return path


def _speeds(t: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``(T,)`` speeds at the samples: the path length per second around each one."""
    step = np.linalg.norm(np.diff(T, axis=0), axis=1) / np.diff(t)  # (T - 1,) between samples
    v = np.empty(t.size)
    v[0], v[-1] = step[0], step[-1]
    v[1:-1] = 0.5 * (step[:-1] + step[1:])
    return v


def _route_vertices(T: np.ndarray, step_m: float) -> np.ndarray:
    """Points of the route every ``step_m`` metres of path (first and last included)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(T, axis=0), axis=1))])
    n = max(int(np.ceil(s[-1] / step_m)), 1)
    at = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(at, s, T[:, i]) for i in range(3)])


def simulate_from_folder(
    folder: str | Path,
    out_dir: str | Path,
    config: SimulatedLogsConfig | None = None,
    *,
    poses: str | Path | None = None,
) -> Path:
    """:func:`simulate_logs` for a KITTI sequence folder (``poses.txt`` and ``times.txt``) or a
    folder with a ``poses.csv`` in a z-up world frame (a render).

    Args:
        folder: the sequence folder.
        out_dir: the folder to write.
        config: the noise model.
        poses: the poses file (default: ``folder/poses.txt``, else ``folder/poses.csv``).

    Raises:
        SlamError: no poses, poses that do not match the frame times.
    """
    folder = Path(folder)
    path = Path(poses) if poses is not None else folder / "poses.txt"
    if poses is None and not path.is_file():
        path = folder / "poses.csv"
    if not path.is_file():
        raise SlamError(f"{folder}: no poses.txt (KITTI) or poses.csv to simulate logs from")
    if path.suffix == ".txt":
        from slam_bridge.frontend.kitti import KittiSequence, read_kitti_poses

        R, T = read_kitti_poses(path)
        times = KittiSequence(folder).timestamps
        if times.size != R.shape[0]:
            raise SlamError(f"{path}: {R.shape[0]} poses for {times.size} frames")
        return simulate_logs(
            times, R, T, out_dir, config, source=str(path), source_to_world=KITTI_TO_WORLD
        )
    from slam_bridge.system.image_slam import read_truth_csv

    times, R, T = read_truth_csv(path)
    return simulate_logs(times, R, T, out_dir, config, source=str(path))

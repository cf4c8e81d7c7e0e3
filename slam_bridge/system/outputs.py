"""The files an image-SLAM run writes (:mod:`slam_bridge.system.image_slam`), each written
atomically.

* :func:`write_trajectory_csv`: one row per keyframe, columns :data:`TRAJECTORY_HEADER`;
* :func:`write_keyframe_log`: the per-keyframe log, columns :data:`KEYFRAME_LOG_HEADER`;
* :func:`write_frame_poses`: a pose for every frame (``frame_poses.csv``), and the same in the
  TUM (``trajectory_tum.txt``) and KITTI (``trajectory_kitti.txt``) formats that evaluation
  tools such as ``evo`` read;
* :func:`write_map_points`: the triangulated points as a PLY point cloud (float64);
* :func:`plot_run`: the top-down plot of the trajectory over the GPS fixes and the truth;
* :func:`write_summary`: the run's figures as JSON.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from geoseg.atomic import atomic_output, atomic_write

__all__ = [
    "TRAJECTORY_HEADER",
    "KEYFRAME_LOG_HEADER",
    "write_trajectory_csv",
    "write_keyframe_log",
    "write_frame_poses",
    "write_map_points",
    "plot_run",
    "write_summary",
]

TRAJECTORY_HEADER = (
    "keyframe,frame,timestamp,tx,ty,tz,qw,qx,qy,qz,r00,r01,r02,r10,r11,r12,r20,r21,r22,"
    "lat_deg,lon_deg,height_m,tracking,segment,in_world"
)
KEYFRAME_LOG_HEADER = (
    "keyframe,frame,timestamp,tracking,segment,observations,pnp_inliers,new_points,gated,"
    "culled,pose_graph_cameras,window_cameras,window_points,kba_ms,kba_iterations,fusion_ms,"
    "fusion_iterations,constraints,fallback,keyframe_ms"
)


def write_trajectory_csv(path: Path, result, frame_of: np.ndarray, georef=None) -> Path:
    """Keyframe poses (world frame, camera-to-world), WGS84 when ``georef`` is known.

    Args:
        path: output file.
        result: the :class:`slam_bridge.slam.loop.SlamResult`.
        frame_of: ``(C,)`` frame index of each keyframe.
        georef: a :class:`geoseg.synth.georef.Georeference` or None (empty WGS84 columns).
    """
    from scipy.spatial.transform import Rotation

    m = result.map
    C = m.num_keyframes
    q = np.zeros((C, 4))
    if result.placed.any():
        q[result.placed] = Rotation.from_matrix(m.R_wc[result.placed]).as_quat()  # (x, y, z, w)
    q = np.column_stack([q[:, 3], q[:, :3]])
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    placed, world = result.placed, result.in_world
    lat = lon = h = np.full(C, np.nan)
    if georef is not None and world.any():
        lat, lon, h = (np.full(C, np.nan) for _ in range(3))
        lat[world], lon[world], h[world] = georef.world_to_wgs84(m.t_wc[world])
    states = {r.keyframe: r.tracking for r in result.records}
    lines = [TRAJECTORY_HEADER]
    for k in range(C):
        if placed[k]:
            pose = ",".join(f"{v:.6f}" for v in m.t_wc[k])
            quat = ",".join(f"{v:.9f}" for v in q[k])
            rot = ",".join(f"{v:.9f}" for v in m.R_wc[k].reshape(-1))
        else:  # a keyframe the start-up could not place: empty pose cells
            pose, quat, rot = ",,", ",,,", ",,,,,,,,"
        wgs = ",," if np.isnan(lat[k]) else f"{lat[k]:.9f},{lon[k]:.9f},{h[k]:.4f}"
        lines.append(
            f"{k},{int(frame_of[k])},{m.timestamps[k]:.6f},{pose},{quat},{rot},{wgs},"
            f"{states.get(k, '')},{int(m.segment[k])},{int(world[k])}"
        )
    return atomic_write(path, "\n".join(lines) + "\n")


def write_keyframe_log(path: Path, result, frame_of: np.ndarray) -> Path:
    """One row per keyframe of :class:`slam_bridge.slam.loop.KeyframeRecord` (times in ms)."""
    m = result.map
    lines = [KEYFRAME_LOG_HEADER]
    for r in result.records:
        k = r.keyframe
        lines.append(
            ",".join(
                str(v)
                for v in (
                    k,
                    int(frame_of[k]),
                    f"{m.timestamps[k]:.6f}",
                    r.tracking,
                    r.segment,
                    r.n_observations,
                    r.n_tracked,
                    r.n_new_points,
                    r.n_gated,
                    r.n_culled,
                    r.n_pose_graph,
                    r.n_cameras,
                    r.n_points,
                    f"{1e3 * r.ba_seconds:.2f}",
                    r.ba_iterations,
                    f"{1e3 * r.fusion_seconds:.2f}",
                    r.fusion_iterations,
                    "+".join(r.constraints),
                    int(r.fallback),
                    f"{1e3 * r.seconds:.2f}",
                )  # fmt: skip
            )
        )
    return atomic_write(path, "\n".join(lines) + "\n")


def write_map_points(path: Path, slam_map) -> Path:
    """The triangulated points as a binary PLY point cloud (world frame), in float64: world-sized
    coordinates (UTM, Lambert-93) keep their millimetres, which float32 would round to ~0.5 m."""
    ids, X = slam_map.triangulated_points()
    X = np.ascontiguousarray(X, dtype="<f8").reshape(-1, 3)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {X.shape[0]}\n"
        "property double x\nproperty double y\nproperty double z\nend_header\n"
    )
    return atomic_write(path, header.encode("ascii") + X.tobytes())


FRAME_POSES_HEADER = "frame,timestamp,tx,ty,tz,qw,qx,qy,qz,source,segment,in_world"


def write_frame_poses(out_dir: Path, poses, names=None) -> list[Path]:
    """A pose for every frame (:class:`slam_bridge.slam.frame_poses.FramePoses`).

    Writes ``frame_poses.csv`` (columns :data:`FRAME_POSES_HEADER`, empty pose cells for a frame
    without one), ``trajectory_tum.txt`` (``timestamp tx ty tz qx qy qz qw``, the frames with a
    pose) and ``trajectory_kitti.txt`` (12 numbers per frame with a pose: row-major 3x4
    ``[R_wc | t_wc]``). All in the run's frame: the world frame once georeferenced.

    Returns:
        The three paths.
    """
    from scipy.spatial.transform import Rotation

    has = poses.has_pose
    q = np.full((has.size, 4), np.nan)  # (x, y, z, w)
    if has.any():
        q[has] = Rotation.from_matrix(poses.R_wc[has]).as_quat()
        q[has] *= np.where(q[has][:, 3:] < 0, -1.0, 1.0)
    rows, tum, kitti = [FRAME_POSES_HEADER], [], []
    for i in range(has.size):
        t = poses.timestamps[i]
        if has[i]:
            p = poses.t_wc[i]
            cells = (
                ",".join(f"{v:.6f}" for v in p)
                + ","
                + ",".join(f"{v:.9f}" for v in (q[i, 3], *q[i, :3]))
            )
            tum.append(
                f"{t:.6f} "
                + " ".join(f"{v:.6f}" for v in p)
                + " "
                + " ".join(f"{v:.9f}" for v in q[i])
            )
            P = np.column_stack([poses.R_wc[i], p])
            kitti.append(" ".join(f"{v:.9e}" for v in P.reshape(-1)))
        else:
            cells = ",,,,,,"
        rows.append(
            f"{i},{t:.6f},{cells},{poses.source[i]},{int(poses.segment[i])},"
            f"{int(poses.in_world[i])}"
        )
    return [
        atomic_write(out_dir / "frame_poses.csv", "\n".join(rows) + "\n"),
        atomic_write(out_dir / "trajectory_tum.txt", "\n".join(tum) + "\n"),
        atomic_write(out_dir / "trajectory_kitti.txt", "\n".join(kitti) + "\n"),
    ]


def plot_run(path: Path, result, inputs, *, title: str = "") -> Path:
    """Top view of the keyframes over the GPS fixes (and the ground truth when known)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = result.map
    fig, ax = plt.subplots(figsize=(7, 6))
    if inputs.truth is not None:
        ax.plot(inputs.truth[2][:, 0], inputs.truth[2][:, 1], "k-", lw=2, label="ground truth")
    if inputs.gps_xy is not None:
        ax.plot(inputs.gps_xy[:, 0], inputs.gps_xy[:, 1], "x", color="0.5", ms=3, label="GPS")
    shown = result.in_world if result.in_world.any() else result.placed
    for s in np.unique(m.segment[shown]):
        sel = shown & (m.segment == s)
        ax.plot(m.t_wc[sel, 0], m.t_wc[sel, 1], "-", lw=1.2, label=f"SLAM segment {s}")
    lost = [r.keyframe for r in result.records if r.tracking == "lost" and shown[r.keyframe]]
    if lost:
        ax.plot(m.t_wc[lost, 0], m.t_wc[lost, 1], "rv", ms=6, label="tracking lost")
    ax.set_aspect("equal")
    world = result.in_world.any()
    ax.set_xlabel("x east (m)" if world else "x (first camera frame)")
    ax.set_ylabel("y north (m)" if world else "y (first camera frame)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    return atomic_write(path, buf.getvalue())


def write_summary(path: Path, summary: dict) -> Path:
    """The run's figures (written last: a folder without it is an unfinished run)."""
    with atomic_output(path, "w") as f:
        json.dump(summary, f, indent=1, sort_keys=True)
        f.write("\n")
    return Path(path)

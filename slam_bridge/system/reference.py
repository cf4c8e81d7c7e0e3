"""A run's keyframes measured against a reference trajectory: the ground truth of a synthetic
drive, or, on a drive without one, a refined run (``geoseg slam refine``, the thesis's pseudo
ground truth, §3.7).

:func:`read_trajectory` reads either kind of file: a run's (or a refined run's) ``trajectory.csv``
(its keyframes in the world frame) or a ``poses.csv`` of true poses (columns ``timestamp, tx,
ty, tz, r00 .. r22``, as a render writes it). :func:`compare_trajectories` pairs the estimate's
poses with the reference's of the same time and gives the errors, with no alignment: both are
in the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam_bridge.csv_columns import read_columns
from slam_bridge.errors import SlamError

__all__ = ["Trajectory", "read_trajectory", "compare_trajectories"]

_POSE_COLUMNS = ["timestamp", "tx", "ty", "tz"] + [f"r{i}{j}" for i in range(3) for j in range(3)]


@dataclass
class Trajectory:
    """Timed poses in the world frame.

    Attributes:
        timestamps: ``(N,)`` seconds, increasing.
        R_wc: ``(N, 3, 3)`` camera-to-world rotations.
        t_wc: ``(N, 3)`` optical centres.
        source: the file it was read from.
    """

    timestamps: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    source: str = ""


def read_trajectory(path: str | Path) -> Trajectory:
    """The world-frame poses of a run folder (its ``trajectory.csv``), a ``trajectory.csv`` or
    a ``poses.csv``.

    Raises:
        SlamError: no such file or folder, a folder without ``trajectory.csv``, missing
            columns, no pose in the world frame, times that do not increase.
    """
    path = Path(path)
    if path.is_dir():
        if not (path / "trajectory.csv").is_file():
            raise SlamError(
                f"{path}: no trajectory.csv: expected the folder of `geoseg slam run` or "
                "`geoseg slam refine`, or a poses.csv"
            )
        path = path / "trajectory.csv"
    cols = read_columns(path, _POSE_COLUMNS, optional=["in_world"])
    keep = np.ones(cols["timestamp"].size, dtype=bool)
    if "in_world" in cols:  # a run's keyframes: the ones in the world frame, with a pose
        keep = cols["in_world"] > 0.5
    for n in _POSE_COLUMNS:
        keep &= np.isfinite(cols[n])
    if not keep.any():
        raise SlamError(f"{path}: no pose in the world frame")
    t = cols["timestamp"][keep]
    if np.any(np.diff(t) <= 0):
        raise SlamError(f"{path}: timestamps must increase")
    R = np.stack([cols[f"r{i}{j}"][keep] for i in range(3) for j in range(3)], axis=1)
    T = np.column_stack([cols["tx"][keep], cols["ty"][keep], cols["tz"][keep]])
    return Trajectory(t, R.reshape(-1, 3, 3), T, str(path))


def compare_trajectories(
    estimate: Trajectory, reference: Trajectory, tolerance_s: float = 1e-3
) -> dict:
    """Errors of ``estimate``'s poses against ``reference``'s pose at the same time.

    Args:
        estimate: e.g. a run's keyframes.
        reference: the truth, or a refined run.
        tolerance_s: two poses are of the same time when this close.

    Returns:
        ``matched`` (poses of the estimate with a reference pose), ``unmatched``,
        ``translation_error_m`` (mean horizontal error), ``translation_error_3d_m``,
        ``translation_error_max_m`` (horizontal) and ``rotation_error_deg`` (mean).

    Raises:
        SlamError: no pose of the estimate has a reference pose within ``tolerance_s``.
    """
    from slam_bridge.evaluation.metrics import rotation_errors

    tr = reference.timestamps
    i = np.clip(np.searchsorted(tr, estimate.timestamps), 1, max(tr.size - 1, 1))
    i = np.where(
        np.abs(tr[i - 1] - estimate.timestamps) <= np.abs(tr[i] - estimate.timestamps), i - 1, i
    ) if tr.size > 1 else np.zeros(estimate.timestamps.size, np.int64)  # fmt: skip
    ok = np.abs(tr[i] - estimate.timestamps) <= tolerance_s
    if not ok.any():
        raise SlamError(
            f"{estimate.source or 'estimate'}: no pose has a pose of "
            f"{reference.source or 'the reference'} within {tolerance_s} s (same drive and "
            "clock expected)"
        )
    j = i[ok]
    d = estimate.t_wc[ok] - reference.t_wc[j]
    e_h = np.linalg.norm(d[:, :2], axis=1)
    e_r = np.degrees(rotation_errors(estimate.R_wc[ok], reference.R_wc[j]))
    return {
        "matched": int(ok.sum()),
        "unmatched": int((~ok).sum()),
        "translation_error_m": float(e_h.mean()),
        "translation_error_3d_m": float(np.linalg.norm(d, axis=1).mean()),
        "translation_error_max_m": float(e_h.max()),
        "rotation_error_deg": float(e_r.mean()),
    }

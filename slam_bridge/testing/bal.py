"""Reading the BAL ("Bundle Adjustment in the Large") format, for tests and benches.

**BAL** (Agarwal et al. 2010) text file::

    <num_cameras> <num_points> <num_observations>
    <camera_index> <point_index> <x> <y>          (num_observations lines)
    <r0> <r1> <r2> <t0> <t1> <t2> <f> <k1> <k2>    (9 values per camera, one per line)
    <X> <Y> <Z>                                    (3 values per point, one per line)

BAL's camera model: ``P = R X + t`` with ``R = exp(hat(r))`` (Rodrigues), ``p = -P / P_z`` (the
camera looks down its ``-z`` axis), ``p' = f (1 + k1 |p|^2 + k2 |p|^4) p``; the observation
``(x, y)`` is ``p'`` (origin at the image centre, ``y`` up).

**Conversion to this package's convention** (OpenCV camera frame, ``X_w = R_wc X_c + t_wc``):
BAL's camera frame is OpenCV's flipped by ``F = diag(1, -1, -1)``, so ``X_c = F (R X + t)``,
``R_wc = R^T F`` and ``t_wc = -R^T t`` (the optical centre). The normalised image point is
``(p_x, -p_y)``, hence with ``K_i = [[f_i, 0, 0], [0, f_i, 0], [0, 0, 1]]`` an undistorted BAL
observation ``(x_u, y_u)`` becomes the pixel ``uv = (x_u, -y_u)``. :func:`bal_to_calibrated`
holds each camera's ``f, k1, k2`` fixed and undistorts the observations (inverting the radial
polynomial by Newton iterations on the radius), so the calibrated bundle adjustment of
:mod:`slam_bridge.ba.solvers.lm` runs on real BAL problems.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoseg.atomic import atomic_write
from geoseg.errors import check_finite, check_shape
from slam_bridge.errors import SlamError
from slam_bridge.geometry.lie import so3_exp, so3_log

logger = logging.getLogger(__name__)

__all__ = [
    "BALProblem",
    "CalibratedProblem",
    "read_bal",
    "write_bal",
    "bal_project",
    "bal_to_calibrated",
    "poses_to_bal",
    "undistort_bal",
]

_F = np.diag([1.0, -1.0, -1.0])


@dataclass
class BALProblem:
    """A BAL problem, as stored in the file.

    Attributes:
        cameras: ``(C, 9)`` ``[r (3), t (3), f, k1, k2]`` per camera.
        points: ``(P, 3)`` world points.
        obs_cameras: ``(M,)`` int.
        obs_points: ``(M,)`` int.
        obs_xy: ``(M, 2)`` observations ``(x, y)`` in BAL's convention.
    """

    cameras: np.ndarray
    points: np.ndarray
    obs_cameras: np.ndarray
    obs_points: np.ndarray
    obs_xy: np.ndarray

    def __post_init__(self) -> None:
        self.cameras = np.asarray(self.cameras, dtype=np.float64)
        self.points = np.asarray(self.points, dtype=np.float64)
        self.obs_cameras = np.asarray(self.obs_cameras, dtype=np.int64).reshape(-1)
        self.obs_points = np.asarray(self.obs_points, dtype=np.int64).reshape(-1)
        self.obs_xy = np.asarray(self.obs_xy, dtype=np.float64)
        M = self.obs_cameras.size
        check_shape("cameras", self.cameras, (None, 9))
        check_shape("points", self.points, (None, 3))
        check_shape("obs_points", self.obs_points, (M,))
        check_shape("obs_xy", self.obs_xy, (M, 2))
        for name in ("cameras", "points", "obs_xy"):
            check_finite(name, getattr(self, name))
        if M and (self.obs_cameras.min() < 0 or self.obs_cameras.max() >= self.cameras.shape[0]):
            raise SlamError("BAL: observation camera index out of range")
        if M and (self.obs_points.min() < 0 or self.obs_points.max() >= self.points.shape[0]):
            raise SlamError("BAL: observation point index out of range")

    def cost(self) -> float:
        """``sum ||bal_project - obs||^2`` (BAL's own formula; no 1/2)."""
        r = bal_project(self.cameras[self.obs_cameras], self.points[self.obs_points]) - self.obs_xy
        return float(np.sum(r * r))


@dataclass
class CalibratedProblem:
    """A BAL problem in this package's convention, intrinsics held fixed.

    Attributes:
        K: ``(C, 3, 3)`` per-camera calibration ``diag(f, f, 1)`` (principal point 0).
        R_wc: ``(C, 3, 3)``.
        t_wc: ``(C, 3)``.
        X_w: ``(P, 3)``.
        obs_cameras: ``(M,)``.
        obs_points: ``(M,)``.
        uv: ``(M, 2)`` undistorted observations (pixels, OpenCV axes).
        k1: ``(C,)`` BAL radial coefficients (kept for writing back).
        k2: ``(C,)``.
    """

    K: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    X_w: np.ndarray
    obs_cameras: np.ndarray
    obs_points: np.ndarray
    uv: np.ndarray
    k1: np.ndarray
    k2: np.ndarray


def _read_bal_text(path: Path) -> str:
    """The text of a BAL file, decompressing ``.bz2``/``.gz``; SlamError for anything else."""
    import bz2
    import gzip
    import zlib

    opener = {".bz2": bz2.open, ".gz": gzip.open}.get(path.suffix.lower())
    try:
        if opener is not None:
            with opener(path, "rt", encoding="ascii") as handle:
                return handle.read()
        return path.read_text(encoding="ascii")
    except UnicodeDecodeError:
        raise SlamError(
            f"read_bal: {path} is not a BAL text file (binary content; a compressed file needs "
            "its .bz2/.gz suffix)"
        ) from None
    except (OSError, EOFError, zlib.error, ValueError) as err:  # bad archives
        raise SlamError(
            f"read_bal: {path}: corrupt or truncated {path.suffix or 'text'} file "
            f"({type(err).__name__}: {err})"
        ) from None


def read_bal(path: str | Path) -> BALProblem:
    """Read a BAL text file (optionally ``.bz2``/``.gz`` compressed).

    Args:
        path: the file.

    Returns:
        A :class:`BALProblem`.

    Raises:
        SlamError: missing, binary or corrupt file; a header that is not three counts >= 0;
            a body with fewer or more numbers than the header announces; non-finite or
            non-integer observations (the message names the file).
    """
    path = Path(path)
    if not path.is_file():
        raise SlamError(f"read_bal: no such file {path}")
    tokens = _read_bal_text(path).split()
    if len(tokens) < 3:
        raise SlamError(f"read_bal: {path} has no header (3 counts: cameras, points, observations)")
    try:
        C, P, M = (int(v) for v in tokens[:3])
    except ValueError:
        raise SlamError(
            f"read_bal: {path}: the header must be 3 integer counts (cameras, points, "
            f"observations), got {' '.join(tokens[:3])!r}"
        ) from None
    if min(C, P, M) < 0:
        raise SlamError(
            f"read_bal: {path}: negative count in the header (cameras {C}, points {P}, "
            f"observations {M})"
        )
    need = 4 * M + 9 * C + 3 * P
    if len(tokens) - 3 != need:
        what = "trailing numbers" if len(tokens) - 3 > need else "numbers missing"
        raise SlamError(
            f"read_bal: {path}: expected {need} values after the header ({C} cameras, {P} "
            f"points, {M} observations), got {len(tokens) - 3} ({what})"
        )
    try:
        data = np.array(tokens[3:], dtype=np.float64)
    except ValueError as exc:
        raise SlamError(f"read_bal: {path}: malformed number ({exc})") from None
    obs = data[: 4 * M].reshape(M, 4)
    cams = data[4 * M : 4 * M + 9 * C].reshape(C, 9)
    pts = data[4 * M + 9 * C : need].reshape(P, 3)
    if not np.all(np.isfinite(data)):
        raise SlamError(f"read_bal: {path}: NaN or infinite values")
    if np.any(obs[:, :2] != np.round(obs[:, :2])):
        raise SlamError(f"read_bal: {path}: non-integer camera/point index")
    logger.debug("read_bal: %s C=%d P=%d M=%d", path, C, P, M)
    try:
        return BALProblem(
            cams, pts, obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64), obs[:, 2:]
        )
    except SlamError as err:
        raise SlamError(f"read_bal: {path}: {err}") from None


def write_bal(path: str | Path, problem: BALProblem) -> Path:
    """Write a BAL text file (full float64 precision, ``repr`` round trip).

    Args:
        path: destination (written atomically: temp file + rename).
        problem: a :class:`BALProblem`.

    Returns:
        The path written.
    """
    path = Path(path)
    C, P, M = problem.cameras.shape[0], problem.points.shape[0], problem.obs_cameras.size
    lines = [f"{C} {P} {M}"]
    lines += [
        f"{c} {p} {x!r} {y!r}"
        for c, p, x, y in zip(
            problem.obs_cameras.tolist(),
            problem.obs_points.tolist(),
            problem.obs_xy[:, 0].tolist(),
            problem.obs_xy[:, 1].tolist(),
        )
    ]
    lines += [repr(v) for v in problem.cameras.reshape(-1).tolist()]
    lines += [repr(v) for v in problem.points.reshape(-1).tolist()]
    return atomic_write(path, "\n".join(lines) + "\n")


def bal_project(cameras: np.ndarray, X: np.ndarray) -> np.ndarray:
    """BAL's projection (module docstring), vectorised.

    Args:
        cameras: ``(N, 9)`` camera of each point.
        X: ``(N, 3)`` world points.

    Returns:
        ``(N, 2)`` predicted observations ``p'`` (NaN where ``P_z == 0``).
    """
    cameras = np.asarray(cameras, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    R = so3_exp(cameras[:, :3])
    Pc = (R @ X[:, :, None])[:, :, 0] + cameras[:, 3:6]
    z = Pc[:, 2:]
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(z != 0, -Pc[:, :2] / np.where(z != 0, z, 1.0), np.nan)
    n2 = np.sum(p * p, axis=1, keepdims=True)
    f, k1, k2 = cameras[:, 6:7], cameras[:, 7:8], cameras[:, 8:9]
    return f * (1.0 + k1 * n2 + k2 * n2 * n2) * p


def undistort_bal(
    xy: np.ndarray, f: np.ndarray, k1: np.ndarray, k2: np.ndarray, iterations: int = 20
) -> np.ndarray:
    """Invert BAL's radial distortion ``q = (1 + k1 |p|^2 + k2 |p|^4) p`` by Newton on ``|p|``.

    Args:
        xy: ``(M, 2)`` distorted observations ``p'``.
        f: ``(M,)`` focal lengths.
        k1: ``(M,)``.
        k2: ``(M,)``.
        iterations: Newton iterations (quadratic convergence; 20 is plenty).

    Returns:
        ``(M, 2)`` undistorted observations ``f p`` (BAL axes).
    """
    q = np.asarray(xy, dtype=np.float64) / f[:, None]
    s = np.linalg.norm(q, axis=1)
    rho = s.copy()
    for _ in range(iterations):
        r2 = rho * rho
        g = rho * (1 + k1 * r2 + k2 * r2 * r2) - s
        dg = 1 + 3 * k1 * r2 + 5 * k2 * r2 * r2
        rho = rho - g / np.where(np.abs(dg) > 1e-12, dg, 1e-12)
    r2 = rho * rho
    bad = ~np.isfinite(rho) | (np.abs(rho * (1 + k1 * r2 + k2 * r2 * r2) - s) > 1e-9 * (1 + s))
    if np.any(bad):
        raise SlamError(
            f"undistort_bal: Newton did not converge for {int(bad.sum())} observations "
            "(radius beyond the distortion polynomial's monotonic range)"
        )
    scale = np.where(s > 0, rho / np.where(s > 0, s, 1.0), 1.0)
    return f[:, None] * q * scale[:, None]


def bal_to_calibrated(problem: BALProblem, undistort: bool = True) -> CalibratedProblem:
    """Convert to this package's convention with fixed intrinsics (module docstring).

    Args:
        problem: a :class:`BALProblem`.
        undistort: undistort the observations with each camera's ``k1, k2`` (if False the
            distortion is ignored, which is exact only when ``k1 = k2 = 0``).

    Returns:
        A :class:`CalibratedProblem`; its reprojection residuals, once the predicted pixels are
        re-distorted, equal BAL's (with ``y`` negated).
    """
    cams = problem.cameras
    C = cams.shape[0]
    R = so3_exp(cams[:, :3])
    t = cams[:, 3:6]
    f, k1, k2 = cams[:, 6], cams[:, 7], cams[:, 8]
    if np.any(f <= 0):
        raise SlamError("bal_to_calibrated: non-positive focal length")
    R_wc = np.swapaxes(R, 1, 2) @ _F
    t_wc = -(np.swapaxes(R, 1, 2) @ t[:, :, None])[:, :, 0]
    K = np.zeros((C, 3, 3))
    K[:, 0, 0] = f
    K[:, 1, 1] = f
    K[:, 2, 2] = 1.0
    oc = problem.obs_cameras
    xy = undistort_bal(problem.obs_xy, f[oc], k1[oc], k2[oc]) if undistort else problem.obs_xy
    uv = np.column_stack([xy[:, 0], -xy[:, 1]])
    return CalibratedProblem(
        K, R_wc, t_wc, problem.points.copy(), oc.copy(), problem.obs_points.copy(), uv, k1, k2
    )


def poses_to_bal(R_wc: np.ndarray, t_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of the pose conversion: ``(C, 3, 3)``, ``(C, 3)`` -> BAL ``r (C, 3)``, ``t (C, 3)``."""
    R = _F @ np.swapaxes(np.asarray(R_wc, dtype=np.float64), 1, 2)  # R = F R_wc^T
    t = -(R @ np.asarray(t_wc, dtype=np.float64)[:, :, None])[:, :, 0]
    return so3_log(R), t

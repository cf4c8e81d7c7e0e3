"""Camera rigs and driving: routes along the street network, smooth poses, frame timestamps.

Two rigs, as in the thesis's sequences:

- ``car``: forward-looking camera ~1.5 m above the road, 1 m ahead of the vehicle reference
  point, optical axis along the direction of motion (following the terrain's pitch).
- ``tram``: side-looking camera ~2 m above the road, optical axis horizontal-ish and orthogonal
  to the motion (looking right by default), image x axis pointing backwards.

The car drives in the middle of the right-hand lane (``WorldConfig.lane_offset``), the tram on
the street centreline (its tracks). Both turn at junctions without U-turns, preferring streets
not driven yet (so long routes close loops), slow down in curves (lateral acceleration
<= 2.5 m/s^2, longitudinal <= 1.5 m/s^2) and follow the terrain (pitch and roll from its normal).

Camera poses are camera-to-world: ``X_w = R_wc X_c + t_wc``, OpenCV camera frame (x right,
y down, z forward).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.ndimage import gaussian_filter1d

from geoseg.errors import GeosegError, check_positive
from geoseg.synth.world import World

logger = logging.getLogger(__name__)

RigName = Literal["car", "tram"]

RIG_DEFAULTS: dict[str, dict[str, float]] = {
    "car": {"height": 1.5, "speed": 11.0, "hfov": 70.0, "forward": 1.0},
    "tram": {"height": 2.0, "speed": 7.0, "hfov": 70.0, "forward": 0.0},
}

LATERAL_ACCEL = 2.5  # m/s^2, the most a curve may ask
LONGITUDINAL_ACCEL = 1.5  # m/s^2
MIN_SPEED_SHARE = 0.25  # speeds never drop below this share of the cruise speed
PATH_STEP = 0.5  # m, resampling of the route
CORNER_SMOOTHING = 6.0  # m, Gaussian sigma applied to the lane path


@dataclass
class Trajectory:
    """Frame-by-frame ground truth of a drive (``T`` frames).

    Attributes:
        timestamps: `(T,)` float64 seconds, strictly increasing, starting at 0.
        R_wc: `(T, 3, 3)` float64 camera-to-world rotations (OpenCV camera frame).
        t_wc: `(T, 3)` float64 camera centres, world frame, metres.
        vehicle_xyz: `(T, 3)` float64 vehicle reference point on the road surface.
        vehicle_heading: `(T,)` float64 world yaw, rad (0 = +x east, counter-clockwise).
        speed: `(T,)` float64 m/s.
        rig: ``car`` or ``tram``.
        K: `(3, 3)` float64 pinhole intrinsics.
        image_size: ``(W, H)`` pixels.
    """

    timestamps: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    vehicle_xyz: np.ndarray
    vehicle_heading: np.ndarray
    speed: np.ndarray
    rig: str
    K: np.ndarray
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])


def pinhole_K(width: int, height: int, hfov_deg: float = 70.0) -> np.ndarray:
    """Pinhole intrinsics with square pixels and the principal point at the image centre.

    Pixel ``(u, v)`` integer coordinates are pixel centres (OpenCV), so ``cx = (W - 1) / 2``.

    Args:
        width: image width W, pixels.
        height: image height H, pixels.
        hfov_deg: horizontal field of view, degrees, in (0, 180).

    Returns:
        `(3, 3)` float64 K.
    """
    check_image_size((width, height))
    if not 0 < float(hfov_deg) < 180:
        raise GeosegError(f"hfov_deg: expected a number in (0, 180), got {hfov_deg}")
    f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0, 0, 1.0]])


def check_image_size(image_size) -> tuple[int, int]:
    """``(W, H)`` as two positive ints, else GeosegError naming ``image_size``."""
    try:
        w, h = image_size
    except (TypeError, ValueError):
        raise GeosegError(f"image_size: expected (W, H), got {image_size!r}") from None
    for name, v in (("W", w), ("H", h)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
            raise GeosegError(f"image_size: expected positive integers (W, H), got {name}={v!r}")
    return int(w), int(h)


def drive(
    world: World,
    *,
    rig: RigName = "car",
    length_m: float = 200.0,
    speed_mps: float | None = None,
    fps: float = 10.0,
    seed: int = 0,
    image_size: tuple[int, int] = (320, 240),
    hfov_deg: float | None = None,
    camera_height: float | None = None,
    side: Literal["right", "left"] = "right",
    lane_offset: float | None = None,
) -> Trajectory:
    """Drive a route through the street network and return the per-frame ground truth.

    Args:
        world: the city.
        rig: ``car`` (forward camera, ~1.5 m) or ``tram`` (side camera, ~2 m).
        length_m: distance driven, metres.
        speed_mps: cruise speed (defaults: car 11 m/s, tram 7 m/s); slower in curves.
        fps: frame rate, Hz.
        seed: picks the start street and the turns.
        image_size: ``(W, H)`` pixels, for K.
        hfov_deg: horizontal field of view (default 70).
        camera_height: camera height above the road (defaults: car 1.5 m, tram 2.0 m).
        side: tram only: which side the camera looks at.
        lane_offset: metres to the right of the street centreline (defaults: car in the middle
            of the right-hand lane, ``WorldConfig.lane_offset``; tram on the centreline, like
            a tram on its tracks).

    Returns:
        The trajectory.

    Raises:
        GeosegError: unknown rig/side, non-positive length, speed, fps or sizes.
    """
    if rig not in RIG_DEFAULTS:
        raise GeosegError(f"rig: expected one of {sorted(RIG_DEFAULTS)}, got {rig!r}")
    if side not in ("right", "left"):
        raise GeosegError(f"side: expected 'right' or 'left', got {side!r}")
    defaults = RIG_DEFAULTS[rig]
    speed_mps = defaults["speed"] if speed_mps is None else speed_mps
    hfov_deg = defaults["hfov"] if hfov_deg is None else hfov_deg
    camera_height = defaults["height"] if camera_height is None else camera_height
    check_positive("length_m", length_m)
    check_positive("speed_mps", speed_mps)
    check_positive("fps", fps)
    check_positive("camera_height", camera_height)
    width, height = check_image_size(image_size)
    K = pinhole_K(width, height, hfov_deg)
    if not world.streets:
        raise GeosegError("world: the street network is empty")

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1789]))
    path_xy, s_start = _route(world, rng, length_m)
    if lane_offset is None:
        lane_offset = world.config.lane_offset if rig == "car" else 0.0
    half = world.config.street_width / 2
    if not -half < float(lane_offset) < half:
        raise GeosegError(
            f"lane_offset: expected a number in (-{half:g}, {half:g}) (the carriageway), "
            f"got {lane_offset}"
        )
    lane = float(lane_offset)
    xy, heading, arc = _lane_path(path_xy, lane)
    s_end = s_start + length_m
    if s_end > arc[-1]:
        raise GeosegError(f"length_m: the route is only {arc[-1] - s_start:.0f} m long")

    # speed profile: cruise, slowed by curvature, limited acceleration both ways
    curvature = np.abs(np.gradient(np.unwrap(heading), arc))
    curvature = gaussian_filter1d(curvature, 2.0)
    v = np.minimum(speed_mps, np.sqrt(LATERAL_ACCEL / np.maximum(curvature, 1e-9)))
    v = np.maximum(v, MIN_SPEED_SHARE * speed_mps)
    ds = np.diff(arc)
    for i in range(1, len(v)):
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * LONGITUDINAL_ACCEL * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * LONGITUDINAL_ACCEL * ds[i]))
    time_at = np.concatenate([[0.0], np.cumsum(ds / (0.5 * (v[1:] + v[:-1])))])
    t0 = np.interp(s_start, arc, time_at)
    t1 = np.interp(s_end, arc, time_at)
    n_frames = int(np.floor((t1 - t0) * fps)) + 1
    timestamps = np.arange(n_frames) / float(fps)
    s_frames = np.interp(t0 + timestamps, time_at, arc)

    pos = np.stack([np.interp(s_frames, arc, xy[:, 0]), np.interp(s_frames, arc, xy[:, 1])], 1)
    yaw = np.interp(s_frames, arc, np.unwrap(heading))
    speed = np.interp(s_frames, arc, v)
    z = world.terrain_height(pos)
    vehicle_xyz = np.concatenate([pos, z[:, None]], axis=1)
    up = world.terrain_normal(pos)
    flat = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)
    forward = flat - (flat * up).sum(1, keepdims=True) * up
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(forward, up)
    down = -up
    if rig == "car":
        axes = (right, down, forward)
        t_wc = vehicle_xyz + camera_height * up + defaults["forward"] * forward
    else:
        look = right if side == "right" else -right
        axes = (np.cross(down, look), down, look)
        t_wc = vehicle_xyz + camera_height * up
    R_wc = np.stack(axes, axis=2)
    logger.info(
        "drove %s route: %.0f m, %d frames at %.1f fps, mean speed %.1f m/s",
        rig,
        length_m,
        n_frames,
        fps,
        speed.mean(),
    )
    return Trajectory(
        timestamps=timestamps,
        R_wc=R_wc,
        t_wc=t_wc,
        vehicle_xyz=vehicle_xyz,
        vehicle_heading=np.mod(yaw + np.pi, 2 * np.pi) - np.pi,
        speed=speed,
        rig=rig,
        K=K,
        image_size=(width, height),
    )


def _route(world: World, rng: np.random.Generator, length_m: float) -> tuple[np.ndarray, float]:
    """A random walk over the street network.

    Returns:
        `(P, 2)` centreline polyline in driving order, and the arc length where driving starts
        (inside the first street, so that frame 0 is not on a junction).
    """
    edges = world.road_graph.edges
    n_nodes = len(world.road_graph.nodes)
    adjacency: list[list[int]] = [[] for _ in range(n_nodes)]
    for e, (a, b) in enumerate(edges):
        adjacency[a].append(e)
        adjacency[b].append(e)
    visits = np.zeros(len(edges), dtype=np.int64)
    edge = int(rng.integers(len(edges)))
    forward = bool(rng.random() < 0.5)
    pieces = []
    first_len = world.streets[edge].length
    s_start = rng.uniform(0.2, 0.6) * first_len
    total = -s_start
    margin = 60.0 + 0.05 * length_m  # the smoothed lane path cuts the corners short
    while total < length_m + margin:
        street = world.streets[edge]
        line = street.centerline if forward else street.centerline[::-1]
        pieces.append(line if not pieces else line[1:])
        total += street.length
        visits[edge] += 1
        node = edges[edge][1] if forward else edges[edge][0]
        options = [e for e in adjacency[node] if e != edge] or [edge]
        fewest = min(visits[e] for e in options)
        options = [e for e in options if visits[e] == fewest]
        edge = int(options[int(rng.integers(len(options)))])
        forward = bool(edges[edge][0] == node)
    return np.concatenate(pieces), float(s_start)


def _lane_path(path_xy: np.ndarray, lane_offset: float):
    """Shift into the right-hand lane, resample and smooth the corners.

    The raw polyline is offset first (mitre joins) and the lane is smoothed after: offsetting
    the smoothed centreline instead puts a cusp on the inside of every turn whose smoothed
    radius is below the lane offset (the car spun through tens of degrees in a frame there).

    Args:
        path_xy: `(P, 2)` centreline polyline.
        lane_offset: metres to the right.

    Returns:
        xy `(N, 2)` lane points, heading `(N,)` rad, arc length `(N,)` along the lane path.
    """
    steps = np.linalg.norm(np.diff(path_xy, axis=0), axis=1)
    keep = np.concatenate([[True], steps > 1e-6])
    lane = _offset_polyline(path_xy[keep], lane_offset)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(lane, axis=0), axis=1))])
    s = np.arange(0.0, arc[-1], PATH_STEP)
    xy = np.stack([np.interp(s, arc, lane[:, 0]), np.interp(s, arc, lane[:, 1])], 1)
    xy = gaussian_filter1d(xy, CORNER_SMOOTHING / PATH_STEP, axis=0, mode="nearest")
    d = np.gradient(xy, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    lane_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    return xy, heading, lane_arc


def _offset_polyline(path_xy: np.ndarray, offset: float) -> np.ndarray:
    """The polyline shifted ``offset`` metres to its right: mitre joins, except a bevel (the two
    segment ends) on the outside of a turn sharper than 120 degrees, where a mitre runs away.

    Args:
        path_xy: `(P, 2)` polyline without repeated points, `P >= 2`.
        offset: metres to the right (negative: left).

    Returns:
        `(Q, 2)` shifted polyline, `Q >= P`.
    """
    u = np.diff(path_xy, axis=0)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    right = np.stack([u[:, 1], -u[:, 0]], axis=1)
    points = [path_xy[0] + offset * right[0]]
    for i in range(1, len(path_xy) - 1):
        n0, n1 = right[i - 1], right[i]
        turns_right = u[i - 1, 0] * u[i, 1] - u[i - 1, 1] * u[i, 0] < 0
        outside = turns_right != (offset > 0)
        if float(u[i - 1] @ u[i]) > -0.5 or not outside:
            points.append(path_xy[i] + offset * (n0 + n1) / (1.0 + float(n0 @ n1)))
        else:
            points += [path_xy[i] + offset * n0, path_xy[i] + offset * n1]
    points.append(path_xy[-1] + offset * right[-1])
    return np.asarray(points)

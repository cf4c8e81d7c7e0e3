"""A run's map as one compact, versioned file (``map.npz``): what a global bundle adjustment
needs once the run is over (:mod:`slam_bridge.system.refine`).

``geoseg slam run`` writes it beside its trajectory (:func:`save_map`); :func:`load_map` reads
it back as a :class:`SavedMap`. The file is a NumPy ``.npz`` archive (no pickled objects) of
the arrays below, written atomically; ``format_version`` is :data:`MAP_FORMAT_VERSION` and a
reader refuses any other.

========================  ==============  =====================================================
key                       shape           meaning
========================  ==============  =====================================================
``format_version``        ``()``          :data:`MAP_FORMAT_VERSION`
``K``                     ``(3, 3)``      intrinsics
``image_size``            ``(2,)``        ``(W, H)`` pixels
``timestamps``            ``(C,)``        keyframe times, seconds
``frame``                 ``(C,)``        each keyframe's frame index
``R_wc``, ``t_wc``        ``(C, 3, 3)``,  keyframe poses (camera-to-world; NaN: not placed)
                          ``(C, 3)``
``segment``               ``(C,)``        segment of each keyframe
``in_world``              ``(C,)``        the keyframe's pose is in the world frame
``tracking``              ``(C,)``        tracking state of each keyframe (text)
``down_c``                ``(C, 3)``      world down measured in each keyframe's image (NaN:
                                          not measured; :mod:`slam_bridge.frontend.
                                          vertical_lines`)
``X_w``                   ``(P, 3)``      points (NaN: never triangulated)
``triangulated``          ``(P,)``        the point has a position
``obs_keyframe``,         ``(M,)``        observations: keyframe, point, pixel, and whether
``obs_point``,            ``(M, 2)``      the run still used it (False: rejected as outlier)
``obs_uv``,
``obs_active``
``facade``, ``facade_weight``  ``(P,)``   the run's building association (facade row of its
                                          ``--buildings`` table, -1: none; weight), when it
                                          had one (else absent)
``association``           ``()``          its method (``bayes``, ``dirichlet``, ``raycast``)
``gps_bias_timestamps``,  ``(F,)``,       the GPS's bias as the run estimated it last (from
``gps_bias_xy``,          ``(F, 2)``,     the building model, :mod:`slam_bridge.bridge.
``gps_bias_var``          ``(F,)``        gps_bias`) at each fix's time and its variance per
                                          axis (m²), when it did (else absent)
``base_timestamps``,      ``(B,)``,       the fixes an image base gave the run (``--base``:
``base_xy``,              ``(B, 2)``,     camera positions, NaN: none) and their weights,
``base_weight``           ``(B,)``        when it had one (else absent)
``camera_height_m``       ``()``          rig: camera height above the road
``antenna_c``             ``(3,)``        rig: GPS antenna in the camera frame
``frame_timestamps``      ``(F,)``        every frame's time (for per-frame poses)
``georef``                ``(3,)``        world origin (lat, lon, alt) or NaN: none
========================  ==============  =====================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoseg.atomic import atomic_output
from slam_bridge.errors import SlamError

__all__ = [
    "MAP_FILE",
    "MAP_FORMAT_VERSION",
    "SavedMap",
    "save_map",
    "load_map",
    "saved_map",
    "map_arrays",
]

MAP_FILE = "map.npz"
MAP_FORMAT_VERSION = 1
_REQUIRED = (
    "format_version", "K", "image_size", "timestamps", "frame", "R_wc", "t_wc", "segment",
    "in_world", "tracking", "down_c", "X_w", "triangulated", "obs_keyframe", "obs_point", "obs_uv",
    "obs_active", "camera_height_m", "antenna_c", "frame_timestamps", "georef",
)  # fmt: skip


@dataclass
class SavedMap:
    """A run's map as :func:`load_map` reads it (the module docstring's arrays).

    Attributes:
        facade: ``(P,)`` the run's facade of each point (-1: none), or None (no association).
        facade_weight: ``(P,)`` its weight, or None.
        association: the association's method, or None.
        gps_bias_timestamps: ``(F,)`` times of the run's GPS bias estimate, or None.
        gps_bias_xy: ``(F, 2)`` the estimate (``fix = true + bias``), metres, or None.
        gps_bias_var: ``(F,)`` its variance per axis (half the covariance's trace), m², or None.
        base_timestamps: ``(B,)`` times of the image base's fixes, or None (no base).
        base_xy: ``(B, 2)`` the fixes (the camera's position; NaN: none), or None.
        base_weight: ``(B,)`` their weights, per square metre, or None.
        georef: ``(3,)`` origin latitude, longitude, altitude, or None.
    """

    K: np.ndarray
    image_size: tuple[int, int]
    timestamps: np.ndarray
    frame: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray
    segment: np.ndarray
    in_world: np.ndarray
    tracking: np.ndarray
    down_c: np.ndarray
    X_w: np.ndarray
    triangulated: np.ndarray
    obs_keyframe: np.ndarray
    obs_point: np.ndarray
    obs_uv: np.ndarray
    obs_active: np.ndarray
    camera_height_m: float
    antenna_c: np.ndarray
    frame_timestamps: np.ndarray
    facade: np.ndarray | None = None
    facade_weight: np.ndarray | None = None
    association: str | None = None
    gps_bias_timestamps: np.ndarray | None = None
    gps_bias_xy: np.ndarray | None = None
    gps_bias_var: np.ndarray | None = None
    base_timestamps: np.ndarray | None = None
    base_xy: np.ndarray | None = None
    base_weight: np.ndarray | None = None
    georef: np.ndarray | None = None

    @property
    def num_keyframes(self) -> int:
        """``C``."""
        return self.timestamps.size

    @property
    def placed(self) -> np.ndarray:
        """``(C,)`` bool: the keyframe has a pose."""
        return np.isfinite(self.t_wc).all(axis=1) & np.isfinite(self.R_wc).all(axis=(1, 2))

    def triangulated_points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (T,), X_w (T, 3))`` of the triangulated points (as
        :meth:`slam_bridge.slam.map.Map.triangulated_points`)."""
        ids = np.flatnonzero(self.triangulated)
        return ids, self.X_w[ids]


def save_map(path: str | Path, result, inputs, bridge=None, gps=None, base=None) -> Path:
    """Write a run's map (module docstring), atomically.

    Args:
        path: the file (``RUN/map.npz``).
        result, inputs, bridge, gps, base: as :func:`map_arrays`.

    Returns:
        ``path``.
    """
    with atomic_output(path, "wb") as f:
        np.savez_compressed(f, **map_arrays(result, inputs, bridge, gps, base))
    return Path(path)


def saved_map(result, inputs, bridge=None, gps=None, base=None) -> SavedMap:
    """A run's map as :func:`load_map` would read it back, without a file (the arguments of
    :func:`map_arrays`; the arrays are copies)."""
    return _saved_map(map_arrays(result, inputs, bridge, gps, base), Path("<memory>"))


def map_arrays(result, inputs, bridge=None, gps=None, base=None) -> dict[str, np.ndarray]:
    """The file's arrays (module docstring) of a run.

    Args:
        result: the run's :class:`slam_bridge.slam.loop.SlamResult`.
        inputs: its :class:`slam_bridge.system.image_slam.SlamInputs` (rig, frame times,
            georeference).
        bridge: its :class:`slam_bridge.bridge.worker.BridgeWorker` (the building association
            is saved), or None.
        gps: its :class:`slam_bridge.slam.fusion.GpsConstraints` (the bias it estimated, if
            any, is saved at its fixes' times), or None.
        base: its :class:`slam_bridge.system.base_fixes.BaseConstraints` (the fixes and their
            weights are saved), or None.
    """
    m = result.map
    frame_t = np.asarray(inputs.frames.timestamps, dtype=np.float64)
    states = {r.keyframe: r.tracking for r in result.records}
    g = inputs.georef
    arrays = {
        "format_version": np.int64(MAP_FORMAT_VERSION),
        "K": m.K,
        "image_size": np.asarray(m.image_size, dtype=np.int64),
        "timestamps": m.timestamps,
        "frame": np.searchsorted(frame_t, m.timestamps).astype(np.int64),
        "R_wc": m.R_wc,
        "t_wc": m.t_wc,
        "segment": m.segment,
        "in_world": result.in_world,
        "tracking": np.array([states.get(k, "") for k in range(m.num_keyframes)], dtype=str),
        "down_c": m.down_c,
        "X_w": m.X_w,
        "triangulated": m.triangulated,
        "obs_keyframe": m.obs_keyframe,
        "obs_point": m.obs_point,
        "obs_uv": m.obs_uv,
        "obs_active": m.obs_active,
        "camera_height_m": np.float64(inputs.rig.camera_height_m),
        "antenna_c": np.asarray(inputs.rig.antenna_c, dtype=np.float64),
        "frame_timestamps": frame_t,
        "georef": np.full(3, np.nan)
        if g is None
        else np.array([g.origin_lat_deg, g.origin_lon_deg, g.origin_alt_m], dtype=np.float64),
    }
    a = None if bridge is None else bridge.constraints.association
    if a is not None:
        facade = np.full(m.num_points, -1, np.int64)
        weight = np.zeros(m.num_points)
        n = min(m.num_points, a.facade.size)  # points newer than the association: none
        facade[:n], weight[:n] = a.facade[:n], a.weight[:n]
        arrays.update(facade=facade, facade_weight=weight, association=np.array(a.method))
    bias = None if gps is None else gps.bias
    if bias is not None and getattr(bias, "history", None):
        # the covariance of the estimate bias.at gives each fix (the same one: made
        # memory_s after the fix, or the latest), as the run's fusion inflated the fix by it
        t = gps.timestamps
        times = np.array([h[1] for h in bias.history])
        var = np.array([0.5 * np.trace(h[3]) for h in bias.history])
        i = np.searchsorted(times, t + bias.config.memory_s, side="right") - 1
        arrays.update(
            gps_bias_timestamps=t,
            gps_bias_xy=np.asarray(bias.at(t)),
            gps_bias_var=np.where(i >= 0, var[np.maximum(i, 0)], 0.0),
        )
    if base is not None:
        arrays.update(base_timestamps=base.timestamps, base_xy=base.xy, base_weight=base.weights)
    return {k: np.array(v) for k, v in arrays.items()}  # copies: the map goes on changing


def load_map(path: str | Path) -> SavedMap:
    """Read a map file written by :func:`save_map`.

    Args:
        path: the file, or a run folder holding :data:`MAP_FILE`.

    Raises:
        SlamError: no such file (a run folder from before the map was saved, or not a run),
            not a map file, another format version, arrays of inconsistent shapes.
    """
    path = Path(path)
    if path.is_dir():
        if not (path / MAP_FILE).is_file():
            raise SlamError(
                f"{path}: no {MAP_FILE} in this folder: expected the output folder of "
                "`geoseg slam run` (runs before the map file existed have none: run it again)"
            )
        path = path / MAP_FILE
    if not path.is_file():
        raise SlamError(f"{path}: no such map file (expected a run's {MAP_FILE})")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as err:
        raise SlamError(f"{path}: not a map file ({err})") from None
    return _saved_map(data, path)


def _saved_map(data: dict[str, np.ndarray], path: Path) -> SavedMap:
    """The :class:`SavedMap` of a file's arrays, checked (``path`` names them in errors)."""
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise SlamError(f"{path}: not a map file of `geoseg slam run` (missing {missing})")
    version = int(data["format_version"])
    if version != MAP_FORMAT_VERSION:
        raise SlamError(
            f"{path}: map format version {version}, this reader knows {MAP_FORMAT_VERSION}"
        )
    georef = data["georef"]
    saved = SavedMap(
        K=data["K"].astype(np.float64),
        image_size=(int(data["image_size"][0]), int(data["image_size"][1])),
        timestamps=data["timestamps"],
        frame=data["frame"],
        R_wc=data["R_wc"],
        t_wc=data["t_wc"],
        segment=data["segment"],
        in_world=data["in_world"].astype(bool),
        tracking=data["tracking"],
        down_c=data["down_c"],
        X_w=data["X_w"],
        triangulated=data["triangulated"].astype(bool),
        obs_keyframe=data["obs_keyframe"],
        obs_point=data["obs_point"],
        obs_uv=data["obs_uv"],
        obs_active=data["obs_active"].astype(bool),
        camera_height_m=float(data["camera_height_m"]),
        antenna_c=data["antenna_c"],
        frame_timestamps=data["frame_timestamps"],
        facade=data.get("facade"),
        facade_weight=data.get("facade_weight"),
        association=str(data["association"]) if "association" in data else None,
        gps_bias_timestamps=data.get("gps_bias_timestamps"),
        gps_bias_xy=data.get("gps_bias_xy"),
        gps_bias_var=data.get("gps_bias_var"),
        base_timestamps=data.get("base_timestamps"),
        base_xy=data.get("base_xy"),
        base_weight=data.get("base_weight"),
        georef=None if np.isnan(georef).any() else georef,
    )
    _check(path, saved)
    return saved


def _check(path: Path, s: SavedMap) -> None:
    """Shapes that agree with each other (a truncated or hand-made file fails here)."""
    C, P, M = s.timestamps.size, s.X_w.shape[0], s.obs_keyframe.size
    expected = {
        "K": (s.K.shape, (3, 3)),
        "R_wc": (s.R_wc.shape, (C, 3, 3)),
        "t_wc": (s.t_wc.shape, (C, 3)),
        "frame": (s.frame.shape, (C,)),
        "segment": (s.segment.shape, (C,)),
        "in_world": (s.in_world.shape, (C,)),
        "tracking": (s.tracking.shape, (C,)),
        "down_c": (s.down_c.shape, (C, 3)),
        "X_w": (s.X_w.shape, (P, 3)),
        "triangulated": (s.triangulated.shape, (P,)),
        "obs_point": (s.obs_point.shape, (M,)),
        "obs_uv": (s.obs_uv.shape, (M, 2)),
        "obs_active": (s.obs_active.shape, (M,)),
        "antenna_c": (s.antenna_c.shape, (3,)),
    }
    if s.facade is not None:
        expected["facade"] = (s.facade.shape, (P,))
        expected["facade_weight"] = (s.facade_weight.shape, (P,))
    bias = (s.gps_bias_timestamps, s.gps_bias_xy, s.gps_bias_var)
    if any(b is None for b in bias) and not all(b is None for b in bias):
        raise SlamError(f"{path}: gps_bias_timestamps, gps_bias_xy, gps_bias_var: all or none")
    fixes = (s.base_timestamps, s.base_xy, s.base_weight)
    if any(b is None for b in fixes) and not all(b is None for b in fixes):
        raise SlamError(f"{path}: base_timestamps, base_xy, base_weight: all or none")
    if s.base_xy is not None:
        B = s.base_timestamps.size
        expected["base_xy"] = (s.base_xy.shape, (B, 2))
        expected["base_weight"] = (s.base_weight.shape, (B,))
    if s.gps_bias_xy is not None:
        F = s.gps_bias_timestamps.size
        expected["gps_bias_xy"] = (s.gps_bias_xy.shape, (F, 2))
        expected["gps_bias_var"] = (s.gps_bias_var.shape, (F,))
    for name, (got, want) in expected.items():
        if got != want:
            raise SlamError(f"{path}: {name}: expected shape {want}, got {got}")
    if M and (s.obs_keyframe.max() >= C or s.obs_point.max() >= P or s.obs_keyframe.min() < 0):
        raise SlamError(f"{path}: observations refer to keyframes or points the map lacks")

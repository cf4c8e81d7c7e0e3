"""Does a run know when it is wrong: consistency checks of a finished run, and its status.

Each check compares the SLAM's estimate with a measurement it should agree with, on the scale
of that measurement's noise, and names the keyframe ranges where it does not:

* ``gps``: each fix (less its estimated bias, when the run estimated one:
  :meth:`~slam_bridge.slam.fusion.GpsConstraints.corrected_fix_at`) against the fused antenna
  position at its keyframe (residual over ``gps_gate_m``);
* ``odometry``: each step between successive keyframes against the distance driven (relative
  miss over ``odometry_gate``: five sigma of a 2 % odometry);
* ``heading``: each camera's heading against its own track's on straight stretches (the
  tangent through the neighbouring keyframes, less the camera's mounting offset: the median
  over the first third of the run), and over chords of at least ``chord_m`` metres the SLAM's track direction
  against the GPS track's (that gate widened to three times the GPS chord's own heading noise,
  from the fixes' median residual), over ``heading_gate_deg``: cameras that look the wrong way
  while the positions follow the fixes, or a trajectory turned away from the GPS track;
* ``tracking``: lost tracking (a new segment) and weak keyframes (few PnP inliers) over
  ``weak_share``; with a GPS, a map never georeferenced;
* recoveries made during the run (a segment georeferenced again when its fixes had left the
  trajectory: :class:`slam_bridge.slam.initialization.TwoViewStart`) are reported too.

The status is ``failed`` when a check fails on more than ``fail_share`` of what it checks (or
the map was never georeferenced despite a GPS), ``degraded`` when any range was flagged, else
``ok``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["HealthConfig", "Health", "assess_run", "flagged_ranges"]

STATUSES = ("ok", "degraded", "failed")


@dataclass
class HealthConfig:
    """Gates of the checks (module docstring).

    Attributes:
        gps_gate_m: a fix further than this from its keyframe's fused antenna position.
        odometry_gate: a keyframe step whose length misses the odometry by this share.
        odometry_min_m: steps shorter than this are not checked (the floor of the noise).
        heading_gate_deg: a heading that misses by more than this, degrees.
        chord_m: shortest chord of the heading check against the GPS track.
        tangent_min_m: shortest span of the tangent a camera's heading is checked against.
        max_turn: the cameras are checked on stretches turning less than this (rad/m: a
            camera 2 m ahead of the rear axle moves 1 deg sideways at 0.01).
        weak_share: share of weak keyframes that makes a run degraded.
        fail_share: share of flagged checks that makes a run failed.
        min_run: consecutive flagged keyframes that make a range (isolated ones are noise).
    """

    gps_gate_m: float = 3.0
    odometry_gate: float = 0.1
    odometry_min_m: float = 0.5
    heading_gate_deg: float = 6.0
    chord_m: float = 20.0
    tangent_min_m: float = 1.0
    max_turn: float = 0.01
    weak_share: float = 0.2
    fail_share: float = 0.5
    min_run: int = 2


@dataclass
class Health:
    """A run's status and why.

    Attributes:
        status: ``ok``, ``degraded`` or ``failed``.
        reasons: one dict per problem: ``check``, ``detail``, ``keyframes`` (``[[first, last],
            ...]`` ranges) and ``severity`` (``degraded`` / ``failed``).
        figures: what the checks measured (medians, shares).
    """

    status: str = "ok"
    reasons: list[dict] = field(default_factory=list)
    figures: dict = field(default_factory=dict)

    def add(self, check: str, severity: str, detail: str, keyframes=()) -> None:
        """Record a problem; the status becomes the worst severity seen."""
        self.reasons.append(
            {"check": check, "severity": severity, "detail": detail, "keyframes": list(keyframes)}
        )
        if STATUSES.index(severity) > STATUSES.index(self.status):
            self.status = severity


def flagged_ranges(ids: np.ndarray, flagged: np.ndarray, min_run: int = 1) -> list[list[int]]:
    """``[[first, last], ...]`` of the runs of at least ``min_run`` consecutive flagged entries.

    Args:
        ids: ``(N,)`` keyframe ids in order.
        flagged: ``(N,)`` bool.
        min_run: shortest run reported.
    """
    out, start = [], None
    for i, f in enumerate(list(flagged) + [False]):
        if f and start is None:
            start = i
        elif not f and start is not None:
            if i - start >= min_run:
                out.append([int(ids[start]), int(ids[i - 1])])
            start = None
    return out


def _heading(v: np.ndarray) -> np.ndarray:
    return np.arctan2(v[..., 1], v[..., 0])


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return np.degrees((np.asarray(a) + np.pi) % (2 * np.pi) - np.pi)


def assess_run(result, *, gps=None, odometry=None, antenna_c=None, config=None) -> Health:
    """The checks of the module docstring on a finished run.

    Args:
        result: the :class:`slam_bridge.slam.loop.SlamResult`.
        gps: the run's :class:`slam_bridge.slam.fusion.GpsConstraints` (``fix_at``), or None.
        odometry: ``distance(t0, t1) -> metres``, or None.
        antenna_c: ``(3,)`` the GPS antenna in the camera frame (None: at the camera).
        config: the gates.

    Returns:
        A :class:`Health`.
    """
    cfg = config or HealthConfig()
    h = Health()
    m = result.map
    records = result.records
    lost = [r.keyframe for r in records if r.tracking == "lost"]
    if lost:
        h.add("tracking", "degraded", f"tracking lost at {len(lost)} keyframe(s): new segments",
              [[k, k] for k in lost])  # fmt: skip
    tracked = [r for r in records if r.tracking in ("tracked", "weak", "bridged")]
    weak = np.array([r.tracking == "weak" for r in tracked])
    if weak.size and weak.mean() > cfg.weak_share:
        ids = np.array([r.keyframe for r in tracked])
        h.add("tracking", "degraded",
              f"{100 * weak.mean():.0f} % of the keyframes tracked on few PnP inliers",
              flagged_ranges(ids, weak, cfg.min_run))  # fmt: skip
    h.figures["weak_keyframe_share"] = float(weak.mean()) if weak.size else 0.0
    for k, before, after in getattr(result, "recoveries", []):
        h.add("gps", "degraded",
              f"the GPS fixes had left the trajectory ({before:.1f} m rms): the segment was "
              f"georeferenced again ({after:.1f} m rms)", [[k, k]])  # fmt: skip
    world = result.in_world
    if gps is not None and not world.any():
        h.add("gps", "failed", "a GPS was given but the map was never georeferenced")
    if gps is not None and world.any():
        _check_gps(h, m, world, gps, antenna_c, cfg)
        _check_heading(h, m, world, gps, cfg)
    if odometry is not None:
        _check_odometry(h, m, result.placed, odometry, cfg)
    return h


def _check_gps(h: Health, m, world, gps, antenna_c, cfg: HealthConfig) -> None:
    ids, res = [], []
    a = np.zeros(3) if antenna_c is None else np.asarray(antenna_c, dtype=np.float64)
    for k in np.flatnonzero(world):
        fix = gps.corrected_fix_at(float(m.timestamps[k]))
        if fix is not None:
            ids.append(k)
            res.append(float(np.linalg.norm(fix - (m.t_wc[k] + m.R_wc[k] @ a)[:2])))
    if not ids:
        return
    res_a = np.array(res)
    bad = res_a > cfg.gps_gate_m
    h.figures["gps_residual_median_m"] = float(np.median(res_a))
    h.figures["gps_flagged_share"] = float(bad.mean())
    if bad.mean() > cfg.fail_share:
        h.add("gps", "failed",
              f"{100 * bad.mean():.0f} % of the fixes are more than {cfg.gps_gate_m:g} m from "
              "the trajectory", flagged_ranges(np.array(ids), bad, 1))  # fmt: skip
    elif flagged_ranges(np.array(ids), bad, cfg.min_run):
        h.add("gps", "degraded",
              f"fixes more than {cfg.gps_gate_m:g} m from the trajectory",
              flagged_ranges(np.array(ids), bad, cfg.min_run))  # fmt: skip


def _check_odometry(h: Health, m, placed, distance, cfg: HealthConfig) -> None:
    ids, miss = [], []
    for k in range(1, m.num_keyframes):
        if not (placed[k] and placed[k - 1]) or m.segment[k] != m.segment[k - 1]:
            continue
        d = float(distance(float(m.timestamps[k - 1]), float(m.timestamps[k])))
        if d < cfg.odometry_min_m:
            continue
        ids.append(k)
        miss.append(np.linalg.norm(m.t_wc[k] - m.t_wc[k - 1]) / d - 1.0)
    if not ids:
        return
    miss_a = np.array(miss)
    bad = np.abs(miss_a) > cfg.odometry_gate
    h.figures["odometry_step_miss_median"] = float(np.median(np.abs(miss_a)))
    h.figures["odometry_flagged_share"] = float(bad.mean())
    severity = "failed" if bad.mean() > cfg.fail_share else "degraded"
    ranges = flagged_ranges(np.array(ids), bad, cfg.min_run)
    if ranges:
        h.add("odometry", severity,
              f"keyframe steps off the odometry's distance by more than "
              f"{100 * cfg.odometry_gate:.0f} % (scale drift)", ranges)  # fmt: skip


def _check_heading(h: Health, m, world, gps, cfg: HealthConfig) -> None:
    gps_noise_m = h.figures.get("gps_residual_median_m", 0.0)
    ks = np.flatnonzero(world)
    pos = m.t_wc[ks, :2]
    yaw = _heading(m.R_wc[ks][:, :, 2])  # the optical axis's heading
    flagged = np.zeros(ks.size, dtype=bool)
    # the cameras against their own track: the tangent from the neighbouring keyframes
    ids, dev = [], []
    for i in range(1, ks.size - 1):
        span = pos[i + 1] - pos[i - 1]
        length = float(np.linalg.norm(span))
        # in a turn a camera ahead of the rear axle moves sideways: straight stretches only
        turn = abs(np.radians(_wrap_deg(yaw[i + 1] - yaw[i - 1]))) / max(length, 1e-6)
        if ks[i + 1] - ks[i - 1] == 2 and length >= cfg.tangent_min_m and turn <= cfg.max_turn:
            ids.append(i)
            dev.append(_wrap_deg(yaw[i] - _heading(span)))
    if len(ids) >= 3:
        dev_a = np.array(dev)
        # the mounting offset from the first third, right after the georeferencing (a run's
        # median would split a failure that covers half of it)
        reference = np.median(dev_a[: max(3, dev_a.size // 3)])
        dev_a = _wrap_deg(np.radians(dev_a - reference))
        flagged[np.array(ids)] |= np.abs(dev_a) > cfg.heading_gate_deg
        h.figures["heading_camera_deviation_max_deg"] = float(np.max(np.abs(dev_a)))
    # the track against the GPS track over chords of chord_m
    fixes = [gps.corrected_fix_at(float(m.timestamps[k])) for k in ks]
    s_along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    track = []
    for i in range(ks.size):
        j = int(np.searchsorted(s_along, s_along[i] + cfg.chord_m))
        if j >= ks.size:
            break
        if fixes[i] is None or fixes[j] is None:
            continue
        chord = pos[j] - pos[i]
        d = _wrap_deg(_heading(chord) - _heading(fixes[j] - fixes[i]))
        # the GPS chord's own heading noise: two fixes of the run's typical error
        noise = np.degrees(np.sqrt(2.0) * gps_noise_m / max(np.linalg.norm(chord), 1e-6))
        track.append(abs(d))
        if abs(d) > max(cfg.heading_gate_deg, 3 * noise):
            flagged[(i + j) // 2] = True
    if track:
        h.figures["heading_track_deviation_max_deg"] = float(np.max(track))
    ranges = flagged_ranges(ks, flagged, cfg.min_run)
    if ranges:
        severity = "failed" if flagged.mean() > cfg.fail_share else "degraded"
        h.add("heading", severity,
              f"the cameras' heading departs from their track, or the track from the GPS "
              f"track, by more than {cfg.heading_gate_deg:g} deg", ranges)  # fmt: skip

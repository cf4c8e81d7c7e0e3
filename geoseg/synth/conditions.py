"""Appearance conditions: the light, the sky and the season, never the geometry.

A :class:`Condition` changes how the renderer shades a frame: sun direction, colour and
strength, ambient (sky) light, the sky gradient, cast shadows, lit windows and street lamps at
night, snow on up-facing surfaces and bare trees in winter.

Buildings, roads, vehicles and objects have the same geometry under every condition, so the
same trajectory rendered under two conditions gives identical labels, depth, normals and
instance ids everywhere except where a tree crown is involved: with ``leaves_on=False``
(``winter``) rays pass through the crown except where they hit a (procedural) branch, so those
pixels show what lies behind the crown and get its label.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geoseg.errors import GeosegError


@dataclass(frozen=True)
class Condition:
    """One appearance condition.

    Attributes:
        name: the condition's name.
        sun_azimuth_deg: sun azimuth, degrees, counter-clockwise from +x (east).
        sun_elevation_deg: sun elevation above the horizon, degrees.
        sun_color: `(3,)` RGB colour of direct sunlight.
        sun_strength: multiplier of direct sunlight (0 = none).
        ambient_color: `(3,)` RGB colour of the sky light.
        ambient_strength: multiplier of the sky light.
        sky_zenith: `(3,)` RGB sky colour overhead.
        sky_horizon: `(3,)` RGB sky colour at the horizon.
        shadows: cast shadow rays towards the sun.
        window_light: share of windows lit (0..1), emissive.
        lamps_on: street lamp heads glow.
        snow: snow cover (0..1) on up-facing surfaces.
        leaves_on: tree crowns are leafy (False: bare branches).
        haze: distance (m) at which the aerial perspective reaches 63 %.
        leaf_color: `(3,)` RGB base colour of the leaves.
        ground_tint: `(3,)` RGB multiplier of grass/terrain.
    """

    name: str
    sun_azimuth_deg: float = 135.0
    sun_elevation_deg: float = 50.0
    sun_color: tuple[float, float, float] = (1.0, 0.97, 0.9)
    sun_strength: float = 0.8
    ambient_color: tuple[float, float, float] = (0.75, 0.82, 0.95)
    ambient_strength: float = 0.5
    sky_zenith: tuple[float, float, float] = (0.25, 0.45, 0.85)
    sky_horizon: tuple[float, float, float] = (0.75, 0.85, 0.95)
    shadows: bool = True
    window_light: float = 0.0
    lamps_on: bool = False
    snow: float = 0.0
    leaves_on: bool = True
    haze: float = 900.0
    leaf_color: tuple[float, float, float] = (0.25, 0.45, 0.15)
    ground_tint: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @property
    def sun_direction(self) -> np.ndarray:
        """`(3,)` unit vector towards the sun, world frame."""
        az, el = np.radians(self.sun_azimuth_deg), np.radians(self.sun_elevation_deg)
        return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


CONDITIONS: dict[str, Condition] = {
    c.name: c
    for c in (
        Condition("summer_day"),
        Condition(
            "overcast",
            sun_strength=0.08,
            sun_color=(0.9, 0.9, 0.9),
            ambient_color=(0.85, 0.86, 0.88),
            ambient_strength=0.95,
            sky_zenith=(0.62, 0.64, 0.67),
            sky_horizon=(0.80, 0.81, 0.82),
            shadows=False,
            haze=500.0,
            leaf_color=(0.22, 0.38, 0.14),
        ),
        Condition(
            "dusk",
            sun_azimuth_deg=280.0,
            sun_elevation_deg=4.0,
            sun_color=(1.0, 0.55, 0.3),
            sun_strength=0.55,
            ambient_color=(0.55, 0.5, 0.7),
            ambient_strength=0.45,
            sky_zenith=(0.18, 0.2, 0.45),
            sky_horizon=(0.95, 0.55, 0.35),
            window_light=0.35,
            lamps_on=True,
            haze=700.0,
        ),
        Condition(
            "night",
            sun_strength=0.0,
            sun_elevation_deg=-20.0,
            ambient_color=(0.35, 0.4, 0.6),
            ambient_strength=0.22,
            sky_zenith=(0.01, 0.015, 0.05),
            sky_horizon=(0.06, 0.07, 0.12),
            shadows=False,
            window_light=0.55,
            lamps_on=True,
            haze=400.0,
        ),
        Condition(
            "winter",
            sun_azimuth_deg=170.0,
            sun_elevation_deg=22.0,
            sun_color=(1.0, 0.95, 0.88),
            sun_strength=0.6,
            ambient_color=(0.82, 0.87, 0.97),
            ambient_strength=0.8,
            sky_zenith=(0.45, 0.58, 0.8),
            sky_horizon=(0.85, 0.88, 0.92),
            snow=1.0,
            leaves_on=False,
            haze=600.0,
            ground_tint=(0.85, 0.8, 0.7),
        ),
        Condition(
            "sun_low",
            sun_azimuth_deg=250.0,
            sun_elevation_deg=12.0,
            sun_color=(1.0, 0.8, 0.6),
            sun_strength=0.95,
            ambient_color=(0.65, 0.7, 0.85),
            ambient_strength=0.4,
            sky_zenith=(0.3, 0.45, 0.8),
            sky_horizon=(0.95, 0.8, 0.6),
            leaf_color=(0.3, 0.45, 0.12),
        ),
    )
}


def get_condition(condition: str | Condition) -> Condition:
    """The condition named ``condition`` (a :class:`Condition` is returned as is).

    Raises:
        GeosegError: unknown name.
    """
    if isinstance(condition, Condition):
        return condition
    if condition not in CONDITIONS:
        raise GeosegError(f"condition: expected one of {sorted(CONDITIONS)}, got {condition!r}")
    return CONDITIONS[condition]

"""Domain randomisation of the synthetic world's appearance: per-frame variations that make the
rendered city look less like one procedural style and more like real streets.

A :class:`RealismConfig` holds probabilities and ranges; :func:`draw_variation` draws one
:class:`Variation` from it (one per training frame, from a seeded generator), and
:meth:`geoseg.synth.renderer.Renderer.render` takes that variation. Every option is off by
default (``RealismConfig()`` draws the identity variation, and ``render(..., variation=None)``
renders exactly as before); :data:`REALISTIC` turns the scene options on.

Most options change only the rendered colours (shop fronts, paint, vehicle colours, ground,
light, sky, shadows, twigs, kerbs, road texture, kerb lines, posters, overcast skies);
``bare_crown_label`` and ``crown_label_cover`` change only the labels; ``p_bare_trees``,
``p_limbs``, ``p_furniture`` and ``p_lens`` change the geometry, with labels that follow it.
What each option does and how it labels: ``docs/real_images.md`` ("Synthetic data that
transfers").
"""

from __future__ import annotations

import colorsys
import dataclasses
from dataclasses import dataclass

import numpy as np

from geoseg.config import check_range
from geoseg.errors import ConfigError
from geoseg.synth.conditions import Condition

# The order of the draws (the random stream of every variation depends on it): first one uniform
# per scene option, together; then, when any is on, the twig, kerb and overcast options'
# together; then each of the later options on its own, in this order, when it is on. An option
# added later draws after these, so the variations drawn before it stay as they were.
_SCENE_PROBABILITIES = (
    "p_shopfront",
    "p_paint",
    "p_vehicle_colour",
    "p_ground",
    "p_light",
    "p_sky",
    "p_shadows",
    "p_bare_trees",
    "p_lens",
)
_TWIG_KERB_OVERCAST_PROBABILITIES = ("p_twigs", "p_kerb", "p_overcast")
_SEPARATE_PROBABILITIES = ("p_kerb_lines", "p_furniture", "p_road_texture", "p_posters", "p_limbs")
_ALL = _SCENE_PROBABILITIES + _TWIG_KERB_OVERCAST_PROBABILITIES + _SEPARATE_PROBABILITIES


@dataclass
class RealismConfig:
    """Probabilities (``p_*``, per frame; 0 = off) and ranges of the appearance variations.

    Attributes:
        p_shopfront: probability that a frame has shop fronts.
        shopfront_share: range of the share of facades with a shop front in such a frame.
        p_paint: probability that a frame repaints facades.
        paint_share: range of the share of facades repainted.
        p_vehicle_colour: probability that a frame recolours vehicles.
        vehicle_colour_share: range of the share of vehicles recoloured.
        p_ground: probability of new road / sidewalk tones.
        road_gain: range of the asphalt brightness multiplier.
        p_light: probability of a new sun direction and light strengths.
        sun_elevation_deg: range of the sun elevation (degrees) in such a frame.
        p_sky: probability of new sky colours and clouds.
        cloud_cover: range of the cloud cover (0 = clear, 1 = overcast).
        p_shadows: probability of cast shadows.
        p_bare_trees: probability of leafless crowns.
        p_lens: probability of lens distortion.
        lens_k1: range of the radial coefficient ``k1``.
        p_twigs: probability that bare crowns get a haze of fine twigs.
        twig_density: range of the share of the background each crown surface covers.
        p_kerb: probability of kerbs, gutters and slab paving.
        slab_m: range of the paving slab edge, metres.
        p_overcast: probability of a flat grey overcast sky with a weak sun.
        p_kerb_lines: probability of painted lines along the kerbs.
        p_furniture: probability of extra street furniture (poles, signs, traffic lights,
            lamp posts, bollards, cabinets; :mod:`geoseg.synth.street_furniture`).
        furniture_spacing_m: range of the mean distance between two items along a street side.
        furniture_kerb_share: share of the extra street furniture standing at the kerb (the
            others stand at the back of the sidewalk, in front of the facades; 1: kerb only).
        furniture_plain_plates: paint the extra furniture's sign plates and lamp heads one
            plain colour each (white, sign blue, red, yellow, green, brown, grey, black) instead
            of the bold stripes and blocks of the city's advertising panels.
        p_road_texture: probability of a smoother (or flat) asphalt.
        road_texture: range of the asphalt's texture contrast (1: as rendered, 0: flat).
        p_posters: probability that a frame has poster hoardings on ground floors.
        poster_share: range of the share of facades with a hoarding in such a frame.
        p_limbs: probability that bare crowns are drawn as branching limbs.
        bare_crown_label: label bare crowns' whole silhouettes ``vegetation``.
        crown_label_cover: with ``bare_crown_label``, label ``vegetation`` only the crown
            pixels where branches stop the ray, the sky shows through, or the fine twigs and
            thin limbs cover at least this share of the pixel (0: the whole silhouette).
    """

    p_shopfront: float = 0.0
    shopfront_share: tuple[float, float] = (0.3, 0.8)
    p_paint: float = 0.0
    paint_share: tuple[float, float] = (0.2, 0.7)
    p_vehicle_colour: float = 0.0
    vehicle_colour_share: tuple[float, float] = (0.5, 1.0)
    p_ground: float = 0.0
    road_gain: tuple[float, float] = (0.75, 1.6)
    p_light: float = 0.0
    sun_elevation_deg: tuple[float, float] = (6.0, 65.0)
    p_sky: float = 0.0
    cloud_cover: tuple[float, float] = (0.0, 1.0)
    p_shadows: float = 0.0
    p_bare_trees: float = 0.0
    p_lens: float = 0.0
    lens_k1: tuple[float, float] = (-0.08, 0.25)
    p_twigs: float = 0.0
    twig_density: tuple[float, float] = (0.15, 0.45)
    p_kerb: float = 0.0
    slab_m: tuple[float, float] = (0.4, 0.9)
    p_overcast: float = 0.0
    p_kerb_lines: float = 0.0
    bare_crown_label: bool = False
    p_furniture: float = 0.0
    furniture_spacing_m: tuple[float, float] = (4.0, 12.0)
    furniture_kerb_share: float = 0.75
    furniture_plain_plates: bool = False
    p_road_texture: float = 0.0
    road_texture: tuple[float, float] = (0.1, 0.8)
    p_posters: float = 0.0
    poster_share: tuple[float, float] = (0.1, 0.4)
    p_limbs: float = 0.0
    crown_label_cover: float = 0.0

    def __post_init__(self) -> None:
        for name in ("bare_crown_label", "furniture_plain_plates"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(
                    f"realism.{name}: expected true or false, got {getattr(self, name)!r}"
                )
        check_range("realism.furniture_kerb_share", self.furniture_kerb_share, 0.0, 1.0)
        check_range("realism.crown_label_cover", self.crown_label_cover, 0.0, 1.0)
        if self.crown_label_cover > 0 and not self.bare_crown_label:
            raise ConfigError(
                "realism.crown_label_cover: it narrows bare_crown_label's crowns; set "
                "bare_crown_label: true (or crown_label_cover: 0)"
            )
        for name in _ALL:
            check_range(f"realism.{name}", getattr(self, name), 0.0, 1.0)
        ranges = {
            "shopfront_share": (0.0, 1.0),
            "paint_share": (0.0, 1.0),
            "vehicle_colour_share": (0.0, 1.0),
            "road_gain": (0.0, None),
            "sun_elevation_deg": (0.5, 89.0),
            "cloud_cover": (0.0, 1.0),
            "lens_k1": (-0.2, 0.6),
            "twig_density": (0.0, 1.0),
            "slab_m": (0.1, 3.0),
            "furniture_spacing_m": (1.0, None),
            "road_texture": (0.0, 1.0),
            "poster_share": (0.0, 1.0),
        }
        for name, (low, high) in ranges.items():
            lo, hi = getattr(self, name)
            check_range(f"realism.{name}[0]", lo, low, high)
            check_range(f"realism.{name}[1]", hi, low, high)
            if lo > hi:
                raise ConfigError(f"realism.{name}: expected low <= high, got {(lo, hi)}")

    @property
    def enabled(self) -> bool:
        """Whether any variation can be drawn (or the bare crowns' labels change)."""
        return self.bare_crown_label or any(getattr(self, n) > 0 for n in _ALL)


REALISTIC = RealismConfig(
    p_shopfront=0.7,
    p_paint=0.7,
    p_vehicle_colour=0.7,
    p_ground=0.7,
    p_light=0.7,
    p_sky=0.7,
    p_shadows=0.5,
    p_bare_trees=0.15,
    p_lens=0.3,
)
"""The scene options on: facades, vehicles, ground, light, sky, shadows, bare trees, lens
(configs: copy its values)."""

REALISTIC_STREETS = dataclasses.replace(
    REALISTIC,
    p_bare_trees=0.4,
    p_twigs=0.8,
    p_kerb=0.7,
    p_overcast=0.25,
    bare_crown_label=True,
)
""":data:`REALISTIC` with more bare trees, labelled as real datasets label them, twig haze,
kerbs and slab paving, overcast skies."""

REALISTIC_FURNISHED = dataclasses.replace(REALISTIC_STREETS, p_kerb_lines=0.6, p_furniture=0.7)
""":data:`REALISTIC_STREETS` with kerb lines and extra street furniture."""


@dataclass(frozen=True)
class Variation:
    """One frame's drawn appearance (the identity when built with no arguments but a seed).

    Attributes:
        seed: keys the per-facade and per-vehicle choices.
        shopfront_share: share of facades with a shop front.
        paint_share: share of facades repainted.
        vehicle_colour_share: share of vehicles recoloured.
        road_gain: asphalt brightness multiplier.
        walk_rgb: `(3,)` paving colour multiplier.
        marking_gain: road marking brightness multiplier.
        sun: ``(azimuth_deg, elevation_deg, strength_gain)`` replacing the condition's sun
            direction and scaling its strength, or None.
        ambient_gain: multiplier of the sky light.
        haze_gain: multiplier of the haze distance.
        sky: ``(zenith rgb, horizon rgb)`` replacing the condition's, or None.
        cloud_cover: 0..1.
        shadows: cast shadows.
        bare_trees: leafless crowns.
        lens_k1: radial distortion coefficient (0: none).
        twig_density: share of the background each bare crown surface covers (0: none).
        kerb_face: brightness of the kerb's face relative to its top stone (0: no kerb drawn).
        slab_m: paving slab edge, metres (0: the default tiles).
        kerb_lines: brightness of the paint along the kerbs (0: none).
        bare_crown_label: bare crowns' whole silhouettes are ``vegetation``.
        furniture_spacing: mean distance between two items of extra street furniture along a
            street side, metres (0: none). Left out of ``repr`` (and so of the frame cache
            keys) at its default; :func:`cache_fields` gives such fields.
        road_texture: contrast of the asphalt's mottling, grit and patches around the frame's
            median asphalt tone (1: as rendered; left out of ``repr`` as above).
        furniture_kerb_share: share of the extra street furniture at the kerb (the others at
            the back of the sidewalk; left out of ``repr`` as above).
        furniture_plain_plates: the extra furniture's plates and lamp heads in plain colours
            (left out of ``repr`` as above).
        poster_share: share of facades whose ground floor is a poster hoarding (0: none; left
            out of ``repr`` as above).
        limbs: bare crowns drawn as branching limbs (left out of ``repr`` as above).
        crown_label_cover: with ``bare_crown_label``, the share of a crown pixel that branches
            and twigs must cover for the pixel to be ``vegetation`` (0: every crown pixel;
            left out of ``repr`` as above).
    """

    seed: int = 0
    shopfront_share: float = 0.0
    paint_share: float = 0.0
    vehicle_colour_share: float = 0.0
    road_gain: float = 1.0
    walk_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    marking_gain: float = 1.0
    sun: tuple[float, float, float] | None = None
    ambient_gain: float = 1.0
    haze_gain: float = 1.0
    sky: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    cloud_cover: float = 0.0
    shadows: bool = False
    bare_trees: bool = False
    lens_k1: float = 0.0
    twig_density: float = 0.0
    kerb_face: float = 0.0
    slab_m: float = 0.0
    kerb_lines: float = 0.0
    bare_crown_label: bool = False
    furniture_spacing: float = dataclasses.field(default=0.0, repr=False)
    road_texture: float = dataclasses.field(default=1.0, repr=False)
    furniture_kerb_share: float = dataclasses.field(default=0.75, repr=False)
    furniture_plain_plates: bool = dataclasses.field(default=False, repr=False)
    poster_share: float = dataclasses.field(default=0.0, repr=False)
    limbs: bool = dataclasses.field(default=False, repr=False)
    crown_label_cover: float = dataclasses.field(default=0.0, repr=False)

    def condition(self, cond: Condition) -> Condition:
        """``cond`` with this variation's light, sky and trees (the sun and sky of daylight
        conditions only: dusk and night keep theirs)."""
        changes: dict = {}
        daylight = cond.sun_elevation_deg > 8.0  # not dusk nor night
        if self.sun is not None and daylight and cond.sun_strength > 0:
            az, el, gain = self.sun
            changes.update(
                sun_azimuth_deg=az,
                sun_elevation_deg=el,
                sun_strength=min(cond.sun_strength * gain, 1.2),
            )
        if self.ambient_gain != 1.0:
            changes["ambient_strength"] = cond.ambient_strength * self.ambient_gain
        if self.haze_gain != 1.0:
            changes["haze"] = cond.haze * self.haze_gain
        if self.sky is not None and daylight:
            changes.update(sky_zenith=self.sky[0], sky_horizon=self.sky[1])
        if self.bare_trees:
            changes["leaves_on"] = False
        return dataclasses.replace(cond, **changes) if changes else cond


def _rgb(values) -> tuple[float, float, float]:
    return tuple(float(v) for v in np.clip(values, 0.0, 1.0))


def draw_variation(cfg: RealismConfig, rng: np.random.Generator) -> Variation:
    """One frame's :class:`Variation` drawn from ``cfg`` (the same draws for the same ``rng``
    state, whatever options are on)."""
    u = rng.random(len(_SCENE_PROBABILITIES))
    fires = {name: bool(u[i] < getattr(cfg, name)) for i, name in enumerate(_SCENE_PROBABILITIES)}
    r = rng.random(18)  # always drawn, so one option's draws do not depend on another's

    def pick(i: int, low_high: tuple[float, float]) -> float:
        return float(low_high[0] + (low_high[1] - low_high[0]) * r[i])

    kw: dict = {"seed": int(rng.integers(2**31))}
    if fires["p_shopfront"]:
        kw["shopfront_share"] = pick(0, cfg.shopfront_share)
    if fires["p_paint"]:
        kw["paint_share"] = pick(1, cfg.paint_share)
    if fires["p_vehicle_colour"]:
        kw["vehicle_colour_share"] = pick(2, cfg.vehicle_colour_share)
    if fires["p_ground"]:
        kw["road_gain"] = pick(3, cfg.road_gain)
        hue, sat, val = r[4], 0.25 * r[5] ** 2, 0.7 + 0.55 * r[6]
        kw["walk_rgb"] = _rgb(np.array(colorsys.hsv_to_rgb(hue, sat, 1.0)) * val)
        kw["marking_gain"] = 0.55 + 0.5 * float(r[7])
    if fires["p_light"]:
        el = pick(8, cfg.sun_elevation_deg)
        kw["sun"] = (360.0 * float(r[9]), el, 0.6 + 0.7 * float(r[10]))
        kw["ambient_gain"] = 0.7 + 0.6 * float(r[11])
        kw["haze_gain"] = 0.5 + 1.5 * float(r[12])
    if fires["p_sky"]:
        grey = float(r[13])  # 0: clear blue, 1: flat white-grey
        blue = np.array([0.22 + 0.2 * r[14], 0.42 + 0.15 * r[14], 0.85])
        white = np.full(3, 0.62 + 0.36 * r[15])
        zenith = blue * (1 - grey) + white * grey
        horizon = np.clip(zenith + 0.25 * (1 - grey) + 0.08, 0.0, 1.0)
        kw["sky"] = (_rgb(zenith), _rgb(horizon))
        kw["cloud_cover"] = pick(17, cfg.cloud_cover)
    kw["shadows"] = fires["p_shadows"]
    kw["bare_trees"] = fires["p_bare_trees"]
    if fires["p_lens"]:
        kw["lens_k1"] = pick(16, cfg.lens_k1)
    kw.update(_draw_later_options(cfg, rng))
    return Variation(**kw)


def _draw_later_options(cfg: RealismConfig, rng: np.random.Generator) -> dict:
    """The :class:`Variation` fields of twigs, kerbs, overcast skies, kerb lines, crown labels,
    street furniture, road texture, posters, limbs and the crown label's cover (options left at
    0 draw nothing: the earlier options' draws stay as they were)."""
    kw: dict = {"bare_crown_label": cfg.bare_crown_label}
    if any(getattr(cfg, name) > 0 for name in _TWIG_KERB_OVERCAST_PROBABILITIES):
        u = rng.random(len(_TWIG_KERB_OVERCAST_PROBABILITIES))
        fires = {
            n: bool(u[i] < getattr(cfg, n)) for i, n in enumerate(_TWIG_KERB_OVERCAST_PROBABILITIES)
        }
        r = rng.random(8)
        if fires["p_twigs"]:
            lo, hi = cfg.twig_density
            kw["twig_density"] = float(lo + (hi - lo) * r[0])
        if fires["p_kerb"]:
            kw["kerb_face"] = float(0.35 + 0.5 * r[1])  # in shade to half lit
            lo, hi = cfg.slab_m
            kw["slab_m"] = float(lo + (hi - lo) * r[2])
        if fires["p_overcast"]:
            grey = 0.55 + 0.4 * r[3]
            tint = np.array([0.97, 0.99, 1.03]) * grey
            kw["sky"] = (_rgb(tint * (0.9 + 0.06 * r[4])), _rgb(tint))
            kw["cloud_cover"] = float(0.6 + 0.4 * r[5])
            # a weak, high sun: soft light with hardly any shading
            kw["sun"] = (360.0 * float(r[6]), 50.0, 0.15 + 0.25 * float(r[7]))
            kw["shadows"] = False
    if cfg.p_kerb_lines > 0:
        u_lines = rng.random(2)
        if u_lines[0] < cfg.p_kerb_lines:
            kw["kerb_lines"] = float(0.45 + 0.5 * u_lines[1])  # worn to fresh paint
    if cfg.p_furniture > 0:
        u_furniture = rng.random(2)
        if u_furniture[0] < cfg.p_furniture:
            lo, hi = cfg.furniture_spacing_m
            kw["furniture_spacing"] = float(lo + (hi - lo) * u_furniture[1])
            # style options: no draws of their own (the other draws stay as they were)
            kw["furniture_kerb_share"] = float(cfg.furniture_kerb_share)
            kw["furniture_plain_plates"] = bool(cfg.furniture_plain_plates)
    if cfg.p_road_texture > 0:
        u_texture = rng.random(2)
        if u_texture[0] < cfg.p_road_texture:
            lo, hi = cfg.road_texture
            kw["road_texture"] = float(lo + (hi - lo) * u_texture[1])
    if cfg.p_posters > 0:
        u_posters = rng.random(2)
        if u_posters[0] < cfg.p_posters:
            lo, hi = cfg.poster_share
            kw["poster_share"] = float(lo + (hi - lo) * u_posters[1])
    if cfg.p_limbs > 0:
        kw["limbs"] = bool(rng.random() < cfg.p_limbs)
    if cfg.crown_label_cover > 0:  # a label rule: no draw of its own
        kw["crown_label_cover"] = float(cfg.crown_label_cover)
    return kw


def cache_fields(variation: Variation) -> dict:
    """The fields of ``variation`` left out of its ``repr`` (options added after the frame
    caches were keyed by ``repr``) that differ from their defaults: ``{name: value}``."""
    return {
        f.name: getattr(variation, f.name)
        for f in dataclasses.fields(variation)
        if not f.repr and getattr(variation, f.name) != f.default
    }

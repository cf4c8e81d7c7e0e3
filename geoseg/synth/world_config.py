"""What defines a synthetic city: :class:`WorldConfig`, its parts and the occluder presets.

Typed dataclasses with their defaults next to them (``configs/world_*.yaml`` only override
them). A :class:`WorldConfig` checks itself when it is made (:func:`_validate`, which
:func:`~geoseg.synth.world.build_world` runs again on the config it gets) and raises a
:class:`~geoseg.errors.ConfigError` naming the key. The configs hold no geometry: the city is
built from them in :mod:`geoseg.synth.world`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Literal

from geoseg.errors import ConfigError

PresetName = Literal["light", "dense_occlusion", "facade_occluded"]


@dataclass
class TerrainConfig:
    """The smooth heightfield.

    Attributes:
        max_grade: the largest slope (rise over run) the three waves can add up to.
        min_wavelength: shortest wave length, metres.
        max_wavelength: longest wave length, metres.
        mesh_spacing: grid spacing of the ground mesh, metres.
        skirt: how far the ground extends beyond the built area, metres (the horizon).
    """

    max_grade: float = 0.05
    min_wavelength: float = 250.0
    max_wavelength: float = 600.0
    mesh_spacing: float = 5.0
    skirt: float = 150.0


@dataclass
class BuildingConfig:
    """Lots along the streets.

    Attributes:
        frontage_min: smallest facade length along the street, metres.
        frontage_max: largest facade length along the street, metres.
        depth_min: smallest lot depth, metres.
        depth_max: largest lot depth, metres.
        storeys_min: fewest storeys.
        storeys_max: most storeys.
        storey_height: height of an upper storey, metres (ground floor is 1.3x).
        setback_max: largest gap between the sidewalk and the facade, metres.
        gap_share: probability of leaving a gap (3-12 m) before a lot.
    """

    frontage_min: float = 10.0
    frontage_max: float = 24.0
    depth_min: float = 10.0
    depth_max: float = 18.0
    storeys_min: int = 3
    storeys_max: int = 8
    storey_height: float = 3.0
    setback_max: float = 1.5
    gap_share: float = 0.15


@dataclass
class OccluderConfig:
    """Occluder densities; ``None`` takes the preset's value (see :data:`PRESETS`).

    Attributes:
        tree_spacing: distance between trees along a tree-lined street side, metres.
        tree_street_share: share of street sides that are tree-lined.
        parked_share: share of kerb slots (every 6 m) holding a parked vehicle.
        moving_per_100m: moving vehicles per 100 m of street.
        lamp_spacing: distance between street lamps along a street, metres.
        shelter_share: probability that a street side has a bus shelter.
        panel_share: probability that a street side has an advertising panel.
        sign_share: probability that a street end has a traffic sign.
    """

    tree_spacing: float | None = None
    tree_street_share: float | None = None
    parked_share: float | None = None
    moving_per_100m: float | None = None
    lamp_spacing: float | None = None
    shelter_share: float | None = None
    panel_share: float | None = None
    sign_share: float | None = None


PRESETS: dict[str, dict[str, float]] = {
    "light": dict(
        tree_spacing=14.0,
        tree_street_share=0.2,
        parked_share=0.12,
        moving_per_100m=0.3,
        lamp_spacing=40.0,
        shelter_share=0.08,
        panel_share=0.08,
        sign_share=0.3,
    ),
    "dense_occlusion": dict(
        tree_spacing=7.5,
        tree_street_share=0.9,
        parked_share=0.75,
        moving_per_100m=0.8,
        lamp_spacing=22.0,
        shelter_share=0.45,
        panel_share=0.45,
        sign_share=0.7,
    ),
    # the thesis's figure 4.13: every street side tree-lined, a shelter and a panel on most,
    # vehicles in most kerb slots; with FACADE_OCCLUDED_LAYOUT they stand close to the facades
    "facade_occluded": dict(
        tree_spacing=6.0,
        tree_street_share=1.0,
        parked_share=0.9,
        moving_per_100m=0.8,
        lamp_spacing=22.0,
        shelter_share=0.9,
        panel_share=0.9,
        sign_share=0.7,
    ),
}

#: The street geometry of the ``facade_occluded`` preset's city (:class:`WorldConfig` fields;
#: ``buildings`` those of :class:`BuildingConfig`): a 1 m sidewalk and facades on its back edge
#: (no setback). The kerb trees' trunks then stand ~1.0 m in front of a facade, the panels
#: ~0.9 m, the shelters' centres ~1.3 m and the parked vehicles' near sides ~1.6 m (medians;
#: with the defaults, 3 m sidewalks and setbacks of up to 1.5 m: 3.2, 1.9-2.9, 1.9-2.0 and
#: 4.5 m). The chapter-4 bench's ``--occluded`` variant builds its cities with it.
FACADE_OCCLUDED_LAYOUT: dict = {"sidewalk_width": 1.0, "buildings": {"setback_max": 0.0}}


@dataclass
class WorldConfig:
    """Everything that defines a synthetic city (with the seed).

    Attributes:
        seed: the random seed; same seed and config give a bit-identical city.
        preset: occluder density preset, ``light``, ``dense_occlusion`` or ``facade_occluded``
            (the last meant with :data:`FACADE_OCCLUDED_LAYOUT`'s street geometry).
        blocks_x: city blocks along x (junctions: ``blocks_x + 1`` per row).
        blocks_y: city blocks along y.
        block_size: distance between neighbouring junctions, metres.
        street_width: carriageway width (2 driving lanes + 2 parking strips), metres.
        parking_width: width of the parking strip along each kerb, metres (0: no parking).
        sidewalk_width: width of each sidewalk, metres.
        node_jitter: random displacement of the junctions, metres.
        curved_street_share: share of the streets that bend.
        curve_amplitude: largest sideways bend of a curved street, metres.
        removed_street_share: share of the inner streets removed (keeps >= 2 per junction).
        terrain: heightfield parameters.
        buildings: lot parameters.
        occluders: occluder densities overriding the preset.
    """

    seed: int = 0
    preset: PresetName = "light"
    blocks_x: int = 4
    blocks_y: int = 3
    block_size: float = 110.0
    street_width: float = 12.0
    sidewalk_width: float = 3.0
    parking_width: float = 2.2
    node_jitter: float = 8.0
    curved_street_share: float = 0.35
    curve_amplitude: float = 10.0
    removed_street_share: float = 0.15
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    buildings: BuildingConfig = field(default_factory=BuildingConfig)
    occluders: OccluderConfig = field(default_factory=OccluderConfig)

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def lane_offset(self) -> float:
        """Distance from the centreline to the middle of a driving lane, metres."""
        return (self.street_width / 2 - self.parking_width) / 2

    def occluder(self, name: str) -> float:
        """The effective occluder density ``name`` (explicit value, else the preset's)."""
        value = getattr(self.occluders, name)
        return float(PRESETS[self.preset][name] if value is None else value)


def _validate(cfg: WorldConfig) -> None:
    def positive(key: str, value: float) -> None:
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            raise ConfigError(f"{key}: expected a number > 0, got {value!r}")

    def share(key: str, value: float | None) -> None:
        if value is not None and not 0.0 <= value <= 1.0:
            raise ConfigError(f"{key}: expected a share in [0, 1], got {value!r}")

    if cfg.preset not in PRESETS:
        raise ConfigError(f"preset: expected one of {sorted(PRESETS)}, got {cfg.preset!r}")
    if isinstance(cfg.seed, bool) or not isinstance(cfg.seed, int) or not 0 <= cfg.seed < 2**63:
        raise ConfigError(f"seed: expected an integer in [0, 2**63), got {cfg.seed!r}")
    for key in ("blocks_x", "blocks_y"):
        value = getattr(cfg, key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(
                f"{key}: expected an integer >= 1 (0 blocks is an empty street network), "
                f"got {value!r}"
            )
    for key in ("block_size", "street_width", "sidewalk_width"):
        positive(key, getattr(cfg, key))
    for key in ("node_jitter", "curve_amplitude"):
        if not getattr(cfg, key) >= 0:
            raise ConfigError(f"{key}: expected a number >= 0, got {getattr(cfg, key)!r}")
    share("curved_street_share", cfg.curved_street_share)
    if not 0 <= cfg.parking_width <= cfg.street_width / 2 - 2.5:
        raise ConfigError(
            f"parking_width: expected a number in [0, street_width / 2 - 2.5 = "
            f"{cfg.street_width / 2 - 2.5:g}] (a driving lane is >= 2.5 m), got {cfg.parking_width}"
        )
    share("removed_street_share", cfg.removed_street_share)
    min_block = cfg.street_width + 2 * cfg.sidewalk_width + 4 * cfg.node_jitter + 10.0
    if cfg.block_size < min_block:
        raise ConfigError(
            f"block_size: expected >= {min_block:g} m for street_width={cfg.street_width:g}, "
            f"sidewalk_width={cfg.sidewalk_width:g}, node_jitter={cfg.node_jitter:g}; "
            f"got {cfg.block_size:g}"
        )
    t = cfg.terrain
    if not 0 <= t.max_grade <= 0.3:
        raise ConfigError(f"terrain.max_grade: expected a number in [0, 0.3], got {t.max_grade}")
    for key in ("min_wavelength", "max_wavelength", "mesh_spacing", "skirt"):
        positive(f"terrain.{key}", getattr(t, key))
    if t.max_wavelength < t.min_wavelength:
        raise ConfigError(
            f"terrain.max_wavelength: expected >= terrain.min_wavelength={t.min_wavelength}, "
            f"got {t.max_wavelength}"
        )
    b = cfg.buildings
    for key in (
        "frontage_min",
        "frontage_max",
        "depth_min",
        "depth_max",
        "storey_height",
        "storeys_min",
        "storeys_max",
    ):
        positive(f"buildings.{key}", getattr(b, key))
    for lo, hi in (("frontage_min", "frontage_max"), ("depth_min", "depth_max")):
        if getattr(b, hi) < getattr(b, lo):
            raise ConfigError(f"buildings.{hi}: expected >= buildings.{lo}, got {getattr(b, hi)}")
    if b.storeys_max < b.storeys_min:
        raise ConfigError(f"buildings.storeys_max: expected >= storeys_min, got {b.storeys_max}")
    if not b.setback_max >= 0:
        raise ConfigError(f"buildings.setback_max: expected >= 0, got {b.setback_max}")
    share("buildings.gap_share", b.gap_share)
    o = cfg.occluders
    for key in ("tree_spacing", "lamp_spacing"):
        value = getattr(o, key)
        if value is not None:
            positive(f"occluders.{key}", value)
    for key in ("tree_street_share", "parked_share", "shelter_share", "panel_share", "sign_share"):
        share(f"occluders.{key}", getattr(o, key))
    if o.moving_per_100m is not None and not o.moving_per_100m >= 0:
        raise ConfigError(f"occluders.moving_per_100m: expected >= 0, got {o.moving_per_100m}")


def with_layout(cfg: WorldConfig, layout: dict) -> WorldConfig:
    """``cfg`` with the fields of ``layout`` replaced (e.g. :data:`FACADE_OCCLUDED_LAYOUT`):
    top-level :class:`WorldConfig` fields, and ``terrain``, ``buildings``, ``occluders`` as dicts
    of their own fields. The result is checked like any :class:`WorldConfig`.

    Raises:
        ConfigError: an unknown field.
    """
    nested = {"terrain", "buildings", "occluders"}
    top = {f.name for f in fields(WorldConfig)}
    changes: dict = {}
    for key, value in layout.items():
        if key not in top or key == "seed":
            raise ConfigError(f"layout: unknown WorldConfig field {key!r}")
        if key in nested:
            part = getattr(cfg, key)
            known = {f.name for f in fields(part)}
            if not isinstance(value, dict) or set(value) - known:
                raise ConfigError(
                    f"layout.{key}: expected a dict of some of {sorted(known)}, got {value!r}"
                )
            value = replace(part, **value)
        changes[key] = value
    return replace(cfg, **changes)

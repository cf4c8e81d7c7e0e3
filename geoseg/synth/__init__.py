"""The synthetic urban world: procedural city, camera rigs and trajectories, ray-cast renderer.

Typical use::

    from geoseg.synth import WorldConfig, build_world, drive, Renderer

    world = build_world(WorldConfig(seed=0, preset="dense_occlusion"))
    traj = drive(world, rig="car", length_m=200.0, fps=10.0)
    for frame in Renderer(world).render_trajectory(traj, "winter"):
        ...  # frame.rgb, frame.labels, frame.normals, frame.depth, frame.instance

The submodules hold the details: :mod:`~geoseg.synth.world` (city; its configs, records,
placement and meshes in ``world_config``, ``world_records``, ``world_layout`` and
``world_meshes``), :mod:`~geoseg.synth.trajectory` (rigs, driving),
:mod:`~geoseg.synth.renderer` (ray casting), :mod:`~geoseg.synth.conditions` (appearance),
:mod:`~geoseg.synth.textures` (procedural textures).
"""

from geoseg.synth.conditions import CONDITIONS, Condition, get_condition
from geoseg.synth.renderer import Frame, Renderer, render
from geoseg.synth.trajectory import Trajectory, drive, pinhole_K
from geoseg.synth.world import (
    Building,
    FacadeTable,
    RoadGraph,
    Street,
    World,
    WorldConfig,
    build_world,
)

__all__ = [
    "CONDITIONS",
    "Building",
    "Condition",
    "FacadeTable",
    "Frame",
    "Renderer",
    "RoadGraph",
    "Street",
    "Trajectory",
    "World",
    "WorldConfig",
    "build_world",
    "drive",
    "get_condition",
    "pinhole_K",
    "render",
]

"""Short rendered drives shared by the front-end tests (rendered once per session, 320x240).

``car_drive`` (forward camera, summer day, light city) and ``tram_drive`` (side camera,
overcast, dense occlusion) are ``geoseg render`` folders in a session temporary directory;
``run_tracks`` runs :class:`ImageTracks` over a folder with a :class:`TruthMap` as the map.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geoseg.synth.export import render_sequence
from geoseg.synth.world import TerrainConfig, WorldConfig
from slam_bridge.evaluate_tracks import RenderTruth, TruthMap
from slam_bridge.frontend.frames import ImageFolder
from slam_bridge.frontend.image_tracks import ImageTracks, ImageTracksConfig

SIZE = (320, 240)
FRAMES = 24


def tiny_world(preset: str) -> WorldConfig:
    return WorldConfig(
        seed=5,
        preset=preset,
        blocks_x=2,
        blocks_y=2,
        block_size=70.0,
        node_jitter=4.0,
        removed_street_share=0.0,
        terrain=TerrainConfig(skirt=60.0, mesh_spacing=6.0),
    )


def _render(root: Path, name: str, rig: str, condition: str, preset: str) -> Path:
    return render_sequence(
        tiny_world(preset),
        root / name,
        FRAMES,
        condition,
        rig,
        image_size=SIZE,
        seed=1,
        progress=False,
        preview_frames=1,
    )


@pytest.fixture(scope="session")
def car_drive(tmp_path_factory) -> Path:
    return _render(tmp_path_factory.mktemp("frontend"), "car", "car", "summer_day", "light")


@pytest.fixture(scope="session")
def tram_drive(tmp_path_factory) -> Path:
    return _render(
        tmp_path_factory.mktemp("frontend"), "tram", "tram", "overcast", "dense_occlusion"
    )


def run_tracks(folder: Path, config: ImageTracksConfig | None = None, distance=None, frames=None,
               points: str = "triangulate"):  # fmt: skip
    """``(keyframes, source, truth map, truth)`` of a full run over ``folder``."""
    frames = frames or ImageFolder(folder)
    truth = RenderTruth(folder)
    src = ImageTracks(frames, config, distance=distance)
    tm = TruthMap(frames.K, frames.image_size, truth.R_wc, truth.t_wc, truth.depth, points=points)
    kfs = []
    while (kf := src.next_keyframe(tm.map)) is not None:
        kfs.append(kf)
        tm.add(kf)
    return kfs, src, tm, truth


def true_distance(folder: Path):
    """``distance(t0, t1) -> metres`` driven, from the true optical centres (as odometry)."""
    truth = RenderTruth(folder)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(truth.t_wc, axis=0), axis=1))])
    return lambda t0, t1: float(
        np.interp(t1, truth.timestamps, s) - np.interp(t0, truth.timestamps, s)
    )


@pytest.fixture
def helpers():
    """``(run_tracks, true_distance, SIZE, FRAMES)`` (test modules cannot import conftest)."""
    return run_tracks, true_distance, SIZE, FRAMES


@pytest.fixture(scope="session")
def car_run(car_drive):
    """Keyframes every 2 m (the default spacing) along the car drive."""
    return run_tracks(car_drive, distance=true_distance(car_drive))


@pytest.fixture(scope="session")
def tram_run(tram_drive):
    return run_tracks(tram_drive, distance=true_distance(tram_drive))

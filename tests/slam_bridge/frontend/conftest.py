"""Short rendered drives shared by the front-end tests (rendered once per session at 640x480, the
resolution the front end's defaults were measured at).

``car_drive`` (forward camera, summer day, light city) and ``tram_drive`` (side camera,
overcast, dense occlusion) are ``geoseg render`` folders in a session temporary directory;
``run_tracks`` runs :class:`ImageTracks` over a folder with a :class:`TruthMap` as the map.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geoseg.synth.export import render_sequence
from slam_bridge.evaluation.tracks import RenderTruth, TruthMap
from slam_bridge.frontend.frames import ImageFolder
from slam_bridge.frontend.image_tracks import ImageTracks, ImageTracksConfig

SIZE = (640, 480)
FRAMES = 24


def _render(root: Path, name: str, rig: str, condition: str, world, size=SIZE) -> Path:
    return render_sequence(
        world,
        root / name,
        FRAMES,
        condition,
        rig,
        image_size=size,
        seed=1,
        progress=False,
        preview_frames=1,
    )


@pytest.fixture(scope="session")
def car_drive(tmp_path_factory, make_tiny_world) -> Path:
    root = tmp_path_factory.mktemp("frontend")
    return _render(root, "car", "car", "summer_day", make_tiny_world())


@pytest.fixture(scope="session")
def car_drive_320(tmp_path_factory, make_tiny_world) -> Path:
    """``car_drive`` at 320x240 (pixel tolerances of the turn tests are set at that size)."""
    root = tmp_path_factory.mktemp("frontend")
    return _render(root, "car", "car", "summer_day", make_tiny_world(), size=(320, 240))


@pytest.fixture(scope="session")
def tram_drive(tmp_path_factory, make_tiny_world) -> Path:
    world = make_tiny_world(preset="dense_occlusion")
    return _render(tmp_path_factory.mktemp("frontend"), "tram", "tram", "overcast", world)


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

"""The bridge beside the loop on the tiny chapter-3 drive, with a stand-in network that labels
the projections of facade landmarks "building" and gives their true normals (the pipeline is
tested, not a network): evidence, eq. 4.14 against the exact facades, building constraints."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from geoseg.synth import build_world
from geoseg.synth.world import SurfaceKind
from slam_bridge.bridge.association import associate_bayes, nearest_facades
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.bridge.facades import Facades
from slam_bridge.bridge.worker import BridgeWorker
from slam_bridge.errors import SlamError
from slam_bridge.experiments.landmarks import sample_landmarks
from slam_bridge.slam.loop import KnownStartPoses, run_slam

OTHER, BUILDING = 0, 1
SCALE = 4  # the stand-in network's maps are a quarter of the image size


class _ImagesOf:
    """The sequence's source with an image per keyframe that encodes the keyframe's index."""

    def __init__(self, source):
        self.source, self.K, self.image_size = source, source.K, source.image_size

    def next_keyframe(self, slam_map=None):
        obs = self.source.next_keyframe(slam_map)
        if obs is None:
            return None
        W, H = self.image_size
        image = np.zeros((H, W, 3), np.uint8)
        image[0, 0, :2] = divmod(obs.frame_index, 256)
        return dataclasses.replace(obs, image=image)


@pytest.fixture(scope="module")
def scene(noisy):
    cfg, seq = noisy
    world = build_world(cfg.world)
    lm = sample_landmarks(world, seq.trajectory.t_wc[:, :2], cfg.landmarks, seed=cfg.seed)
    t = world.facades()
    d = np.einsum("fi,fi->f", t.normal[:, :2], t.p0)
    facades = Facades(t.p0, t.p1, t.z_min, t.z_max, t.normal, d, t.facade_id)
    truth, _ = nearest_facades(facades, lm.X_w, radius_m=0.2)
    truth[lm.kind != SurfaceKind.FACADE] = -1
    W, H = seq.image_size
    maps = []
    o = seq.observations
    for k in range(seq.num_keyframes):
        probs = np.zeros((H // SCALE, W // SCALE, 2))
        probs[..., OTHER] = 0.9
        probs[..., BUILDING] = 0.1
        normals = np.zeros((H // SCALE, W // SCALE, 3))
        sel = np.flatnonzero(o.keyframe == k)
        c = np.clip(
            np.rint((o.uv[sel] + 0.5) / SCALE - 0.5).astype(int),
            0,
            [W // SCALE - 1, H // SCALE - 1],
        )
        facade = lm.kind[o.point[sel]] == SurfaceKind.FACADE
        probs[c[:, 1], c[:, 0]] = np.where(facade[:, None], [0.05, 0.95], [0.95, 0.05])
        normals[c[:, 1], c[:, 0]] = lm.normal_w[o.point[sel]] @ seq.R_wc_true[k]
        maps.append((probs, normals))

    def network(image):
        return maps[int(image[0, 0, 0]) * 256 + int(image[0, 0, 1])]

    return cfg, seq, facades, truth, network


def _run(scene, worker=None, providers=()):
    cfg, seq, *_ = scene
    start = KnownStartPoses(
        seq.R_wc_true, seq.t_wc_true, cfg.slam.tracking.outlier_gate_px, cfg.start_keyframes,
        cfg.slam.mapping,
    )  # fmt: skip
    return run_slam(_ImagesOf(seq.source()), "ba", start, providers, cfg.slam, on_keyframe=worker)


def _worker(scene, network=None, delay_s=0.0, **kwargs):
    _, _, facades, _, stand_in = scene

    def associate(s):
        time.sleep(delay_s)
        return associate_bayes(facades, s.points, s.labels, s.normals, BUILDING, 1.0)

    constraints = BuildingConstraints(facades)
    worker = BridgeWorker(network or stand_in, 2, associate, constraints, **kwargs)
    return worker, constraints


def _error(scene, res):
    return np.linalg.norm(res.map.t_wc - scene[1].t_wc_true, axis=1).mean()


def test_synchronous_bridge(scene):
    """Measured: mean keyframe error 0.147 m (vision) -> 0.033 m, association precision 0.994
    over 358 points; every association used one keyframe after it was computed."""
    truth = scene[3]
    vision = _run(scene)
    worker, constraints = _worker(scene, asynchronous=False)
    bridged = _run(scene, worker, [constraints])
    final = worker.finish(bridged.map)
    assert any("building" in r.constraints for r in bridged.records)
    assert _error(scene, bridged) < 0.5 * _error(scene, vision)
    got = np.flatnonzero(final.associated)
    assert got.size > 100
    assert np.mean(final.facade[got] == truth[got]) > 0.95
    assert set(worker.stats.lags) == {1} and worker.stats.dropped == 0
    again, c2 = _worker(scene, asynchronous=False)
    np.testing.assert_array_equal(_run(scene, again, [c2]).map.t_wc, bridged.map.t_wc)


def test_the_loop_never_waits_for_a_slow_network(scene):
    """A network of 0.2 s per image and an association of 0.1 s: the loop goes on (measured:
    0.02 ms of its time per keyframe), inference jobs beyond ``max_pending`` are dropped and
    associations arrive keyframes late."""
    stand_in = scene[4]

    def slow(image):
        time.sleep(0.2)
        return stand_in(image)

    worker, constraints = _worker(scene, network=slow, delay_s=0.1, max_pending=2)
    res = _run(scene, worker, [constraints])
    worker.finish(res.map)
    assert np.median(worker.stats.main_seconds) < 0.05
    assert worker.stats.dropped > 0 and max(worker.stats.lags) > 1
    assert np.isfinite(res.map.t_wc).all()


def test_a_fixed_lag_makes_a_slow_asynchronous_run_repeatable(scene):
    """``lag_keyframes=2``: a slow network and association in threads, waited for when late,
    give exactly the trajectory of the inline worker with the same lag (and nothing dropped)."""
    stand_in = scene[4]

    def slow(image):
        time.sleep(0.05)
        return stand_in(image)

    inline, c_inline = _worker(scene, asynchronous=False, lag_keyframes=2)
    reference = _run(scene, inline, [c_inline])
    inline.finish(reference.map)
    threaded, c_threaded = _worker(
        scene, network=slow, delay_s=0.05, max_pending=1, lag_keyframes=2
    )
    res = _run(scene, threaded, [c_threaded])
    threaded.finish(res.map)
    assert threaded.stats.dropped == 0 and set(threaded.stats.lags) == {2}
    assert set(inline.stats.lags) == {2}
    np.testing.assert_array_equal(res.map.t_wc, reference.map.t_wc)
    with pytest.raises(SlamError, match="lag_keyframes"):
        _worker(scene, lag_keyframes=0)


def test_a_slow_network_labels_every_few_keyframes(scene):
    """``infer_every=3``: the network sees keyframes 0, 3, 6, ... only; the points still gather
    evidence from them (each is seen in several keyframes) and get associated."""
    stand_in = scene[4]
    seen = []

    def counted(image):
        seen.append(image.shape)
        return stand_in(image)

    worker, constraints = _worker(scene, network=counted, asynchronous=False, infer_every=3)
    res = _run(scene, worker, [constraints])
    final = worker.finish(res.map)
    # keyframe 0 is a start keyframe, with no image from this source
    assert len(seen) == len(range(3, res.map.num_keyframes, 3))
    assert final.associated.sum() > 50


def test_online_snapshots_hold_the_recent_points(scene):
    """With ``recent_keyframes`` an online association sees the triangulated points observed in
    that many latest keyframes, with the same evidence (so the same association) as a snapshot
    of every point; the final association covers every point."""
    _, _, facades, _, stand_in = scene
    recent, taken = 8, []

    def associate(s):
        everything = worker._snapshot(worker.evidence.map, s.keyframe, recent=None).inputs()
        taken.append((s, everything))
        return associate_bayes(facades, s.points, s.labels, s.normals, BUILDING, 1.0)

    constraints = BuildingConstraints(facades)
    worker = BridgeWorker(
        stand_in, 2, associate, constraints, asynchronous=False, recent_keyframes=recent
    )
    m = _run(scene, worker, [constraints]).map
    final = worker.finish(m)
    online = [(s, e) for s, e in taken[:-1] if s.keyframe > recent]
    fewer = 0
    for s, everything in online:
        seen = np.unique(m.obs_point[(m.obs_keyframe >= s.keyframe - recent)
                                     & (m.obs_keyframe <= s.keyframe)])  # fmt: skip
        placed = np.flatnonzero(np.isfinite(everything.points[:, 0]))  # triangulated
        has = np.flatnonzero(np.isfinite(s.points[:, 0]))
        np.testing.assert_array_equal(has, np.intersect1d(seen, placed))
        fewer += has.size < placed.size
        for name in ("points", "mean_probs", "labels", "normals", "centres"):
            np.testing.assert_array_equal(getattr(s, name)[has], getattr(everything, name)[has])
    assert fewer > 0  # older points left out
    assert final.facade.size == m.num_points
    assert np.flatnonzero(final.associated).size > 100


def test_bad_worker_settings(scene):
    with pytest.raises(SlamError, match="associate_every"):
        _worker(scene, associate_every=0)
    with pytest.raises(SlamError, match="infer_every"):
        _worker(scene, infer_every=0)
    with pytest.raises(SlamError, match="recent_keyframes"):
        _worker(scene, recent_keyframes=0)


def test_segmenter_outputs_resizes_and_transposes():
    from geoseg.infer import SegmentationResult
    from slam_bridge.bridge.worker import segmenter_outputs

    seen = []

    def segmenter(image):
        seen.append(image.shape)
        h, w = image.shape[:2]
        probs = np.zeros((1, 3, h, w), np.float32)
        probs[0, 2] = 1.0
        normals = np.zeros((1, 3, h, w), np.float32)
        normals[0, 0] = 1.0
        return SegmentationResult(probs, probs.argmax(1).astype(np.uint8), normals)

    probs, normals = segmenter_outputs(segmenter, (32, 24))(np.zeros((48, 64, 3), np.uint8))
    assert seen == [(24, 32, 3)]
    assert probs.shape == (24, 32, 3) and np.all(probs[..., 2] == 1)
    assert normals.shape == (24, 32, 3) and np.all(normals[..., 0] == 1)
    probs, _ = segmenter_outputs(segmenter)(np.zeros((48, 64, 3), np.uint8))
    assert probs.shape == (48, 64, 3)


def test_geometry_only_worker_runs_no_network(scene):
    """The ray-cast baseline needs positions only: no network, no evidence, associations."""
    _, _, facades, _, _ = scene
    constraints = BuildingConstraints(facades)
    worker = BridgeWorker(
        None,
        2,
        lambda s: associate_bayes(facades, s.points, s.labels, s.normals, BUILDING, 1.0),
        constraints,
        asynchronous=False,
    )
    res = _run(scene, worker, [constraints])
    final = worker.finish(res.map)
    assert worker.stats.inference_seconds == [] and not final.associated.any()


@pytest.mark.parametrize("asynchronous", [False, True])
def test_a_failing_network_stops_the_run_with_its_error(scene, asynchronous):
    """A network that fails (wrong class count here) raises in the main thread, named."""

    def wrong(image):
        probs, normals = scene[4](image)
        return probs[..., :1], normals

    worker, constraints = _worker(scene, network=wrong, asynchronous=asynchronous)
    with pytest.raises(SlamError, match="probs"):  # during the run, or at the latest in finish
        res = _run(scene, worker, [constraints])
        worker.finish(res.map)
    worker.close()

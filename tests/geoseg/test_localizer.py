"""The localisation library entry (geoseg.reloc.localizer) and image bases built from geotagged folders
(geoseg.reloc.base_build, `geoseg base build`)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from geoseg.errors import GeosegError
from geoseg.reloc.base_build import build_image_base, level_camera_rotations, read_source
from geoseg.reloc.image_base import ThumbnailEmbedder, load_image_base
from geoseg.reloc.localizer import Localizer, LocalizerConfig
from geoseg.reloc.retrieval import RetrievalIndex
from geoseg_cli.cli import main


def _images(n: int, seed: int = 0, size=(48, 64)) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [
        cv2.GaussianBlur(rng.integers(0, 256, (*size, 3), dtype=np.uint8), (5, 5), 0)
        for _ in range(n)
    ]


def _save(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _render_like(root: Path, n: int = 4) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """A folder with the layout of a `geoseg render` output (rgb/, poses.csv, camera.json)."""
    images = _images(n)
    R = level_camera_rotations(np.radians(np.arange(n) * 10.0))
    t = np.c_[np.arange(n) * 2.0, np.ones(n), np.full(n, 1.5)]
    header = "frame,timestamp,tx,ty,tz,qw,qx,qy,qz," + ",".join(
        f"r{i}{j}" for i in range(3) for j in range(3)
    )
    rows = [header]
    for i in range(n):
        _save(root / "rgb" / f"{i:06d}.png", images[i])
        vals = [i, 0.1 * i, *t[i], 1, 0, 0, 0, *R[i].ravel()]
        rows.append(",".join(str(v) for v in vals))
    (root / "poses.csv").write_text("\n".join(rows) + "\n")
    K = [[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]]
    (root / "camera.json").write_text(json.dumps({"K": K, "image_size": [64, 48], "fps": 10}))
    return images, R, t


def test_level_camera_rotations_look_along_the_heading() -> None:
    R = level_camera_rotations(np.radians([0.0, 90.0, 200.0]))
    for Ri in R:
        np.testing.assert_allclose(Ri.T @ Ri, np.eye(3), atol=1e-12)
        assert np.linalg.det(Ri) == pytest.approx(1.0)
        np.testing.assert_allclose(Ri[:, 1], [0, 0, -1])  # camera y is down
    np.testing.assert_allclose(R[0][:, 2], [1, 0, 0], atol=1e-12)  # heading 0: east
    np.testing.assert_allclose(R[1][:, 2], [0, 1, 0], atol=1e-12)  # heading 90: north
    np.testing.assert_allclose(R[1][:, 0], [1, 0, 0], atol=1e-12)  # facing north, right is east


def test_a_render_output_becomes_a_base(tmp_path: Path) -> None:
    _, R, t = _render_like(tmp_path / "render")
    out = build_image_base(tmp_path / "render", tmp_path / "base")
    base = load_image_base(out)
    assert base.images == [f"rgb/{i:06d}.png" for i in range(4)]
    np.testing.assert_allclose(base.R_wc, R, atol=1e-9)
    np.testing.assert_allclose(base.t_wc, t)
    np.testing.assert_allclose(base.timestamps, 0.1 * np.arange(4))
    assert base.image_size == (64, 48) and base.K[0, 0] == 60.0
    # a base is itself a source (re-written as is); a second build into the same folder is fine
    again = load_image_base(build_image_base(out, tmp_path / "base2"))
    np.testing.assert_allclose(again.R_wc, R, atol=1e-9)
    build_image_base(tmp_path / "render", tmp_path / "base")


def test_positions_file_gives_level_cameras_along_the_track(tmp_path: Path) -> None:
    src = tmp_path / "photos"
    for i, img in enumerate(_images(4)):
        _save(src / f"p{i}.jpg", img)
    # an L-shaped track: east, east, then north; the last image stands still
    xy = [(0.0, 0.0), (5.0, 0.0), (5.0, 5.0), (5.0, 5.0)]
    rows = ["image,x,y,z"] + [f"p{i}.jpg,{x},{y},10" for i, (x, y) in enumerate(xy)]
    (tmp_path / "pos.csv").write_text("\n".join(rows) + "\n")
    base = load_image_base(
        build_image_base(src, tmp_path / "base", positions=tmp_path / "pos.csv", camera_height_m=2)
    )
    np.testing.assert_allclose(base.t_wc[:, 2], 12.0)
    forward = base.R_wc[:, :, 2]
    np.testing.assert_allclose(forward[0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(forward[1], [np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-12)
    np.testing.assert_allclose(forward[3], [0, 1, 0], atol=1e-12)  # the heading it came with
    # an explicit heading wins over the track
    rows = ["image,x,y,heading_deg"] + [f"p{i}.jpg,{x},{y},180" for i, (x, y) in enumerate(xy)]
    (tmp_path / "pos.csv").write_text("\n".join(rows) + "\n")
    got = read_source(src, positions=tmp_path / "pos.csv")
    np.testing.assert_allclose(got["R_wc"][:, :, 2], [[-1, 0, 0]] * 4, atol=1e-12)


def test_unknown_layouts_and_bad_rows_are_refused(tmp_path: Path) -> None:
    src = tmp_path / "photos"
    _save(src / "a.png", _images(1)[0])
    with pytest.raises(GeosegError, match="positions file"):
        read_source(src)
    (tmp_path / "pos.csv").write_text("image,x\na.png,1\n")
    with pytest.raises(GeosegError, match="missing column"):
        read_source(src, positions=tmp_path / "pos.csv")
    (tmp_path / "pos.csv").write_text("image,x,y\nb.png,1,2\n")
    with pytest.raises(GeosegError, match="b.png not found"):
        read_source(src, positions=tmp_path / "pos.csv")
    (tmp_path / "pos.csv").write_text("image,x,y\na.png,1,nope\n")
    with pytest.raises(GeosegError, match="row 2"):
        read_source(src, positions=tmp_path / "pos.csv")
    with pytest.raises(GeosegError, match="source folder"):
        build_image_base(src, src, positions=tmp_path / "pos.csv")


def _fixed_pose(distance: float):
    """A relative pose that puts the query ``distance`` m straight ahead of each base camera."""

    def relative_pose(idx, query):
        return [
            {
                "ok": True,
                "reason": "",
                "R_ab": np.eye(3),
                "t_dir_ab": np.array([0.0, 0.0, 1.0]),
                "distance_m": distance,
                "n_inliers": None,
            }
            for _ in idx
        ]

    return relative_pose


def test_localizer_retrieves_reranks_and_places_the_query() -> None:
    images = _images(5)
    embed = ThumbnailEmbedder()
    R = level_camera_rotations(np.zeros(5))  # all look east
    t = np.c_[np.arange(5) * 10.0, np.zeros(5), np.full(5, 1.5)]
    loc = Localizer(
        index=RetrievalIndex(embed(images), R_wc=R, t_wc=t),
        embed=embed,
        relative_pose=_fixed_pose(2.0),
        base_names=[f"b{i}" for i in range(5)],
        config=LocalizerConfig(k=2, position_k=1),
    )
    (res,) = loc.localize([images[3]], names=["q"])
    assert res.name == "q" and [m["image"] for m in res.matches][0] == "b3"
    assert res.position["method"] == "ranged rays" and not res.position["degenerate"]
    np.testing.assert_allclose(res.xyz, [32.0, 0.0, 1.5], atol=1e-9)  # 2 m east of b3
    # the GPS window keeps only base images near the fix; outside it nothing matches
    loc.config = LocalizerConfig(k=3, radius_m=5.0)
    (res,) = loc.localize([images[3]], gps=[[11.0, 0.0]])
    assert [m["image"] for m in res.matches] == ["b1"]
    (res,) = loc.localize([images[3]], gps=[[500.0, 0.0]])
    assert res.matches == [] and res.xyz is None and "within 5.0 m" in res.position["reason"]
    with pytest.raises(GeosegError, match="gps"):
        loc.localize([images[3]])
    # a drive along the base through the route filter: each query finds its own base image
    loc.config = LocalizerConfig(k=1, sequence="filter")
    results = loc.localize(images)
    assert [r.matches[0]["image"] for r in results] == [f"b{i}" for i in range(5)]
    assert all(0 < r.matches[0]["sequence_probability"] <= 1 for r in results)


def test_rays_that_do_not_agree_give_the_best_match_position() -> None:
    """Heads out of their depth (a camera unlike their training one): when no two matches'
    ranged rays agree, the position is the best match's camera, not one stray ray."""
    images = _images(5)
    embed = ThumbnailEmbedder()
    R = level_camera_rotations(np.zeros(5))  # all look east (camera z)
    t = np.c_[np.arange(5) * 10.0, np.zeros(5), np.full(5, 1.5)]
    truth = np.array([23.0, 0.0, 1.5])

    def agreeing(idx, query):  # each base camera sees the query where it is
        return [{"ok": True, "reason": "", "R_ab": np.eye(3), "n_inliers": None,
                 "t_dir_ab": np.array([0.0, 0.0, np.sign(truth[0] - t[i, 0])]),
                 "distance_m": abs(truth[0] - t[i, 0])} for i in idx]  # fmt: skip

    def scattered(idx, query):  # sideways, at ranges that contradict each other
        return [{"ok": True, "reason": "", "R_ab": np.eye(3), "n_inliers": None,
                 "t_dir_ab": np.array([(-1.0) ** j, 0.0, 0.0]), "distance_m": 2.0 + 5 * j}
                for j, _ in enumerate(idx)]  # fmt: skip

    for relative_pose, method, expected in (
        (agreeing, "ranged rays", truth),
        (scattered, "best match", t[2]),
    ):
        loc = Localizer(
            index=RetrievalIndex(embed(images), R_wc=R, t_wc=t),
            embed=embed,
            relative_pose=relative_pose,
            base_names=[f"b{i}" for i in range(5)],
            config=LocalizerConfig(k=3),
        )
        (res,) = loc.localize([images[2]])
        assert res.matches[0]["image"] == "b2" and res.position["method"] == method
        np.testing.assert_allclose(res.xyz, expected, atol=1e-6)
    assert "do not agree" in res.position["reason"]
    with pytest.raises(GeosegError, match="min_agreeing_rays"):
        LocalizerConfig(min_agreeing_rays=0)


def test_localizer_config_refuses_bad_values() -> None:
    with pytest.raises(GeosegError, match="k"):
        LocalizerConfig(k=0)
    with pytest.raises(GeosegError, match="radius_m"):
        LocalizerConfig(radius_m=-1)
    with pytest.raises(GeosegError, match="sequence"):
        LocalizerConfig(step_m=3)


def test_base_build_command_then_localize(tmp_path: Path, capsys) -> None:
    images, _, t = _render_like(tmp_path / "render")
    base = tmp_path / "base"
    assert (
        main(
            [
                "base",
                "build",
                str(tmp_path / "render"),
                "--out",
                str(base),
                "--embedding",
                "thumbnail",
            ]
        )
        == 0
    )
    assert list((base / "cache").glob("embeddings_thumbnail*.npz"))
    q = tmp_path / "q.png"
    _save(q, images[2])
    out = tmp_path / "res.json"
    argv = ["localize", str(q), "--base", str(base), "--embedding", "thumbnail"]
    assert main([*argv, "--relative-pose", "essential", "--k", "2", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["queries"][0]["matches"][0]["image"] == "rgb/000002.png"
    assert res["intrinsics"] == "camera.json"


def test_a_render_output_given_as_base_says_how_to_make_one(tmp_path: Path) -> None:
    _render_like(tmp_path / "render")
    with pytest.raises(GeosegError, match="geoseg base build"):
        load_image_base(tmp_path / "render")


class _ConstantHead:
    """A relative-pose head stand-in: fixed outputs per pair."""

    def __init__(self, rotation: float, distances: list[float], predict_distance: bool = True):
        self.rotation, self.distances = rotation, distances
        self.predict_distance = predict_distance

    def __call__(self, feat_a, feat_b) -> dict:
        import torch

        n = feat_a.shape[0]
        return {
            "rotation": torch.full((n, 3), self.rotation),
            "direction": torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1),
            "log_distance": torch.log(torch.tensor(self.distances[:n])),
        }


def test_gated_head_takes_the_near_heads_distance_below_the_gate_only() -> None:
    import torch

    from geoseg.reloc.networks import GatedRelPoseHead, head_relative_poses

    far = _ConstantHead(0.0, [3.0, 4.0, 5.0])
    near = _ConstantHead(0.01, [0.1, 0.29, 0.31])
    gated = GatedRelPoseHead(far, near, near_m=0.3)
    feats = torch.zeros(3, 8, 2, 2)
    out = gated(feats, feats)
    assert out["near"].tolist() == [True, True, False]
    np.testing.assert_allclose(out["log_distance"].exp().numpy(), [0.1, 0.29, 5.0], rtol=1e-6)
    np.testing.assert_allclose(out["rotation"].numpy(), 0.0)  # always the far head's
    poses = head_relative_poses(gated, feats, feats)
    assert [p["distance_m"] for p in poses] == pytest.approx([0.1, 0.29, 5.0], rel=1e-6)
    # a higher gate takes the near head's answer for the third pair too
    out = GatedRelPoseHead(far, near, near_m=0.5)(feats, feats)
    assert out["near"].all()


def test_gated_head_refuses_heads_without_distances_and_bad_gates() -> None:
    from geoseg.reloc.networks import GatedRelPoseHead

    head = _ConstantHead(0.0, [1.0])
    with pytest.raises(GeosegError, match="near: .*distances"):
        GatedRelPoseHead(head, _ConstantHead(0.0, [1.0], predict_distance=False))
    with pytest.raises(GeosegError, match="far: .*distances"):
        GatedRelPoseHead(_ConstantHead(0.0, [1.0], predict_distance=False), head)
    for bad in (0.0, -0.3, float("nan")):
        with pytest.raises(GeosegError, match="near_m"):
            GatedRelPoseHead(head, head, near_m=bad)


def test_shipped_localizer_gates_the_distance_with_the_near_head(tmp_path: Path) -> None:
    from geoseg.pretrained import pretrained_file
    from geoseg.reloc.networks import NEAR_GATE_M, GatedRelPoseHead

    images, _, _ = _render_like(tmp_path / "render")
    base = build_image_base(tmp_path / "render", tmp_path / "base")
    loc = Localizer.from_base(base, embedding="thumbnail", cache=False)
    head = loc.relative_pose.head
    assert isinstance(head, GatedRelPoseHead) and head.near_m == NEAR_GATE_M
    assert "near head" in loc.relative_pose_name
    (res,) = loc.localize([images[1]])
    assert all(m["relative_pose"]["distance_m"] > 0 for m in res.matches)
    # no gate when asked, or with another relative-pose head (the near head is the shipped
    # head's fine-tune)
    for kwargs in ({"near_gate_m": None}, {"relpose_head": pretrained_file("relpose")}):
        loc = Localizer.from_base(base, embedding="thumbnail", cache=False, **kwargs)
        assert not isinstance(loc.relative_pose.head, GatedRelPoseHead)
    with pytest.raises(GeosegError, match="near_gate_m"):
        Localizer.from_base(base, embedding="thumbnail", cache=False, near_gate_m=0.0)

"""`geoseg localize` end to end on tiny image bases, and its clean errors (exit 2)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from geoseg.reloc.image_base import load_image_base, write_poses_csv
from geoseg_cli.cli import main

# the networks-free placeholders (the shipped networks are the default)
PLACEHOLDER = ["--embedding", "thumbnail", "--relative-pose", "essential"]

R_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _save(path: Path, rgb: np.ndarray) -> None:
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def random_base(root: Path, m: int = 5, size=(48, 64), seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    images, names = [], []
    for i in range(m):
        img = cv2.GaussianBlur(rng.integers(0, 256, (*size, 3), dtype=np.uint8), (5, 5), 0)
        _save(root / f"img_{i}.png", img)
        images.append(img)
        names.append(f"img_{i}.png")
    t = np.c_[np.arange(m) * 10.0, np.zeros(m), np.full(m, 1.5)]
    write_poses_csv(root / "poses.csv", names, np.stack([R_NORTH] * m), t)
    return images


def test_end_to_end_placeholder_embedding(tmp_path: Path, capsys) -> None:
    images = random_base(tmp_path / "base")
    q = tmp_path / "queries" / "q.png"
    q.parent.mkdir()
    _save(q, images[3])
    out = tmp_path / "out" / "res.json"
    rc = main(
        [
            "localize",
            *PLACEHOLDER,
            str(q),
            "--base",
            str(tmp_path / "base"),
            "--k",
            "2",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "img_3.png" in text and "placeholder" in text and "position" in text
    res = json.loads(out.read_text())
    assert res["base_size"] == 5 and res["k"] == 2
    (query,) = res["queries"]
    assert [m["rank"] for m in query["matches"]] == [1, 2]
    assert query["matches"][0]["image"] == "img_3.png"
    assert query["matches"][0]["distance"] < 1e-6
    assert query["matches"][0]["base_t_wc"] == [30.0, 0.0, 1.5]
    # identical / unrelated random images: the baseline fails cleanly, no position
    assert not query["matches"][0]["relative_pose"]["ok"]
    assert query["matches"][0]["relative_pose"]["reason"]
    assert query["position"]["degenerate"] and query["position"]["xyz"] is None


def test_gps_window(tmp_path: Path) -> None:
    images = random_base(tmp_path / "base")
    q = tmp_path / "q.png"
    _save(q, images[4])  # duplicate of the image at x = 40 m ...
    gps = tmp_path / "gps.csv"
    gps.write_text("image,x,y\nq.png,0.0,0.0\n")  # ... but GPS says x = 0
    out = tmp_path / "res.json"
    args = ["localize", *PLACEHOLDER, str(q), "--base", str(tmp_path / "base"), "--out", str(out)]
    assert main([*args, "--gps", str(gps), "--radius", "15"]) == 0
    matches = json.loads(out.read_text())["queries"][0]["matches"]
    assert {m["image"] for m in matches} == {"img_0.png", "img_1.png"}
    assert main([*args, "--gps", str(gps), "--radius", "1e-3", "--k", "1"]) == 0
    assert main([*args, "--gps", str(gps), "--radius", "1e-3"]) == 0
    q_res = json.loads(out.read_text())["queries"][0]
    assert [m["image"] for m in q_res["matches"]] == ["img_0.png"]


def test_sequence_overrules_an_aliased_query(tmp_path: Path) -> None:
    """A drive past base images 2-5 whose third view looks exactly like base image 7 (an
    aliased facade): alone it matches image 7; as a drive the route filter places it at 4."""
    images = random_base(tmp_path / "base", m=8)
    names = []
    rng = np.random.default_rng(5)
    for j, i in enumerate([2, 3, 7, 5]):
        noisy = np.clip(images[i] + rng.normal(0, 8, images[i].shape), 0, 255).astype(np.uint8)
        names.append(str(tmp_path / f"q{j}.png"))
        _save(Path(names[-1]), noisy)
    out = tmp_path / "res.json"
    args = ["localize", *PLACEHOLDER, *names, "--base", str(tmp_path / "base"), "--out", str(out)]
    assert main(args) == 0
    single = json.loads(out.read_text())["queries"]
    assert [q["matches"][0]["image"] for q in single] == [f"img_{i}.png" for i in (2, 3, 7, 5)]
    for mode in ("filter", "smooth"):
        seq = [*args, "--sequence", mode, "--step-m", "10"]
        assert main(seq) == 0
        res = json.loads(out.read_text())
        assert res["sequence"] == mode
        third = res["queries"][2]["matches"]
        assert third[0]["image"] == "img_4.png" and third[0]["sequence_probability"] > 0.5
        probs = [m["sequence_probability"] for m in third]
        assert probs == sorted(probs, reverse=True) and sum(probs) <= 1 + 1e-9
        assert [q["matches"][0]["image"] for q in res["queries"]] == [
            f"img_{i}.png" for i in (2, 3, 4, 5)
        ]
    # --gps-sigma is the filter's GPS likelihood: the aliased view alone, its fix at image 4
    gps = tmp_path / "gps.csv"
    gps.write_text("image,x,y\nq2.png,40,0\n")
    one = ["localize", *PLACEHOLDER, names[2], "--base", str(tmp_path / "base"), "--out", str(out)]
    assert main([*one, "--sequence", "filter"]) == 0
    assert json.loads(out.read_text())["queries"][0]["matches"][0]["image"] == "img_7.png"
    assert main([*one, "--sequence", "filter", "--gps", str(gps), "--gps-sigma", "3"]) == 0
    assert json.loads(out.read_text())["queries"][0]["matches"][0]["image"] == "img_4.png"


# ----------------------------------------------------------------------------- geometry

W, H = 640, 480
K = np.array([[500.0, 0.0, (W - 1) / 2], [0.0, 500.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
_PLANES = [  # n . X = c, in-plane basis (e1, e2): a street canyon with a far wall and a road
    (np.array([1.0, 0, 0]), -4.0, np.array([0, 1.0, 0]), np.array([0, 0, 1.0])),
    (np.array([1.0, 0, 0]), 4.0, np.array([0, 1.0, 0]), np.array([0, 0, 1.0])),
    (np.array([0, 1.0, 0]), 25.0, np.array([1.0, 0, 0]), np.array([0, 0, 1.0])),
    (np.array([0, 0, 1.0]), 0.0, np.array([1.0, 0, 0]), np.array([0, 1.0, 0])),
]


def _texture(rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    tex = cv2.resize(rng.uniform(0, 255, (16, 16)).astype(np.float32), (size, size))
    tex = tex.astype(np.uint8)
    for _ in range(4000):
        x, y = (int(v) for v in rng.integers(0, size, 2))
        w, h = (int(v) for v in rng.integers(4, 24, 2))
        grey = int(rng.integers(0, 256))
        if rng.uniform() < 0.5:
            cv2.rectangle(tex, (x, y), (x + w, y + h), grey, -1)
        else:
            cv2.circle(tex, (x, y), w // 2, grey, -1)
    return cv2.GaussianBlur(tex, (3, 3), 0)


def _render(R_wc: np.ndarray, t_wc: np.ndarray, textures) -> np.ndarray:
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ R_wc.T
    best = np.full((H, W), np.inf)
    out = np.zeros((H, W), np.uint8)
    for (n, c, e1, e2), tex in zip(_PLANES, textures):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (c - t_wc @ n) / (rays @ n)
        s = np.where(np.isfinite(s), s, -1.0)
        hit = (s > 0) & (s < best)
        X = t_wc + np.maximum(s, 0.0)[..., None] * rays
        px = ((X @ e1 * 20.0) % tex.shape[1]).astype(np.float32)
        py = ((X @ e2 * 20.0) % tex.shape[0]).astype(np.float32)
        img = cv2.remap(tex, px, py, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        out[hit], best[hit] = img[hit], s[hit]
    return np.repeat(out[..., None], 3, axis=2)


def test_end_to_end_absolute_position_from_essential_baseline(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    textures = [_texture(rng) for _ in _PLANES]
    base = tmp_path / "base"
    base.mkdir()
    R0 = R_NORTH @ _rot("x", -8.0)
    centres = np.array([[-1.5, 0.0, 1.6], [1.5, 0.5, 1.6], [0.0, -2.0, 1.7]])
    Rs = np.stack([_rot("z", yaw) @ R0 for yaw in (5.0, -4.0, 2.0)])
    names = []
    for i, (R, t) in enumerate(zip(Rs, centres)):
        _save(base / f"b{i}.png", _render(R, t, textures))
        names.append(f"b{i}.png")
    write_poses_csv(base / "poses.csv", names, Rs, centres)
    (base / "camera.json").write_text(json.dumps({"K": K.tolist()}))
    q_t = np.array([0.2, 1.5, 1.5])
    q = tmp_path / "query.png"
    _save(q, _render(_rot("z", 1.0) @ R0, q_t, textures))
    out = tmp_path / "res.json"
    assert (
        main(["localize", *PLACEHOLDER, str(q), "--base", str(base), "--k", "3", "--out", str(out)])
        == 0
    )
    res = json.loads(out.read_text())
    assert res["intrinsics"] == "camera.json" and "essential" in res["relative_pose_method"]
    query = res["queries"][0]
    assert len(query["matches"]) == 3 and all(m["relative_pose"]["ok"] for m in query["matches"])
    pos = query["position"]
    assert not pos["degenerate"] and pos["n_rays"] == 3 and pos["n_inliers"] >= 2
    assert np.linalg.norm(np.array(pos["xyz"]) - q_t) < 0.3
    # the query's orientation from each match whose ray is an inlier
    R_q_true = _rot("z", 1.0) @ R0
    for m in query["matches"]:
        if m["rank"] in pos["inlier_ranks"]:
            R_q = np.array(m["relative_pose"]["query_R_wc"])
            cos = (np.trace(R_q.T @ R_q_true) - 1.0) / 2.0
            assert np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) < 1.0


# ----------------------------------------------------------------------------- models


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    from geoseg.infer import save_model_checkpoint
    from geoseg.models.joint import joint
    from geoseg.models.reloc import reloc_head
    from geoseg.models.relpose import relpose_head

    d = tmp_path_factory.mktemp("models")
    return {
        "seg": save_model_checkpoint(joint(), d / "joint.pt", model_name="joint"),
        "reloc": save_model_checkpoint(
            reloc_head(embedding_dim=16),
            d / "reloc.pt",
            model_name="reloc",
            model_config={"embedding_dim": 16},
        ),
        "relpose": save_model_checkpoint(relpose_head(), d / "relpose.pt", model_name="relpose"),
        "relpose_distance": save_model_checkpoint(
            _fixed_distance_head(relpose_head(predict_distance=True), 5.0),
            d / "relpose_distance.pt",
            model_name="relpose",
            model_config={"predict_distance": True},
        ),
    }


def _fixed_distance_head(head, metres: float):
    """A distance head that predicts ``metres`` for every pair (zero weights, bias log m)."""
    import torch

    with torch.no_grad():
        head.regress[-1].weight[6].zero_()
        head.regress[-1].bias[6] = float(np.log(metres))
    return head


def test_with_model_and_heads(tmp_path: Path, checkpoints, capsys) -> None:
    images = random_base(tmp_path / "base", m=3)
    q = tmp_path / "q.png"
    _save(q, images[1])
    out = tmp_path / "res.json"
    args = ["localize", str(q), "--base", str(tmp_path / "base"), "--out", str(out)]
    args += ["--network-size", "none"]  # the tiny test images as they are
    raw = ["--embedding", "layer21", "--relative-pose", "essential", "--network-size", "none"]
    assert main([*args, *raw, "--model", str(checkpoints["seg"])]) == 0
    res = json.loads(out.read_text())
    assert res["embedding"] == "raw layer-21 features"
    assert res["queries"][0]["matches"][0]["image"] == "img_1.png"
    rc = main(
        [
            *args,
            "--model",
            str(checkpoints["seg"]),
            "--reloc-head",
            str(checkpoints["reloc"]),
            "--relpose-head",
            str(checkpoints["relpose"]),
        ]
    )
    assert rc == 0
    res = json.loads(out.read_text())
    assert res["embedding"].startswith("learned") and "head" in res["relative_pose_method"]
    query = res["queries"][0]
    assert query["matches"][0]["image"] == "img_1.png"
    assert all(m["relative_pose"]["ok"] for m in query["matches"])
    assert isinstance(query["position"]["degenerate"], bool)
    # a head with distances: each match gets one, the position comes from ranged rays (one
    # match suffices), matches are re-ranked by distance (ties keep the appearance order)
    head_args = [
        *args,
        "--model",
        str(checkpoints["seg"]),
        "--reloc-head",
        str(checkpoints["reloc"]),
    ]
    rc = main(
        [*head_args, "--relpose-head", str(checkpoints["relpose_distance"]), "--position-k", "1"]
    )
    assert rc == 0
    query = json.loads(out.read_text())["queries"][0]
    assert [m["relative_pose"]["distance_m"] for m in query["matches"]] == pytest.approx([5.0] * 3)
    assert [m["rank"] for m in query["matches"]] == [1, 2, 3]
    assert [m["appearance_rank"] for m in query["matches"]] == [1, 2, 3]
    pos = query["position"]
    assert pos["method"] == "ranged rays" and not pos["degenerate"] and pos["n_rays"] == 1
    first = query["matches"][0]
    base = load_image_base(tmp_path / "base")
    i = first["index"]
    want = base.t_wc[i] + 5.0 * base.R_wc[i] @ np.asarray(first["relative_pose"]["t_dir_ab"])
    np.testing.assert_allclose(pos["xyz"], want, atol=1e-5)
    assert "5.0 m away" in capsys.readouterr().out
    # with the GPS noise given, the equal head distances are fused with the fix's distances:
    # the base at x = 20 m, nearest the fix, comes first
    gps = tmp_path / "gps.csv"
    gps.write_text("image,x,y\nq.png,19.0,0.0\n")
    gps_args = ["--gps", str(gps), "--radius", "100", "--gps-sigma", "2.0"]
    distance_head = ["--relpose-head", str(checkpoints["relpose_distance"])]
    assert main([*head_args, *distance_head, *gps_args]) == 0
    matches = json.loads(out.read_text())["queries"][0]["matches"]
    assert [m["image"] for m in matches] == ["img_2.png", "img_1.png", "img_0.png"]
    w_head, w_gps = 1 / (0.3 * 5.0) ** 2, 1 / 2.0**2
    assert matches[0]["gps_fused_distance_m"] == pytest.approx(
        (w_head * 5.0 + w_gps * 1.0) / (w_head + w_gps)
    )
    # a dominant appearance weight restores the embedding's order; a negative one is refused
    assert main([*head_args, *distance_head, *gps_args, "--appearance-weight", "1e6"]) == 0
    matches = json.loads(out.read_text())["queries"][0]["matches"]
    assert [m["appearance_rank"] for m in matches] == [1, 2, 3]
    err = _error(capsys, [*head_args, *distance_head, *gps_args, "--appearance-weight", "-1"])
    assert "--appearance-weight" in err
    err = _error(capsys, [*head_args, *distance_head, "--gps-sigma", "2.0"])
    assert "--gps-sigma" in err and "--gps" in err
    err = _error(capsys, [*head_args, *distance_head, *gps_args[:-1], "-1"])
    assert "--gps-sigma" in err
    no_distance = ["--relpose-head", str(checkpoints["relpose"])]
    err = _error(capsys, [*head_args, *no_distance, *gps_args])
    assert "--gps-sigma" in err and "predicts distances" in err
    # a head of the wrong kind
    err = _error(
        capsys,
        [*args, "--model", str(checkpoints["seg"]), "--relpose-head", str(checkpoints["reloc"])],
    )
    assert "RelocHead" in err and "RelPoseHead" in err
    # feature maps of mismatched sizes: a query of another size
    big = tmp_path / "big.png"
    _save(big, np.zeros((96, 64, 3), np.uint8))
    base = str(tmp_path / "base")
    err = _error(
        capsys,
        ["localize", str(big), "--base", base, *raw, "--model", str(checkpoints["seg"])],
    )
    assert "big.png: 64x96 pixels" in err and "hold for 64x48 images" in err  # the intrinsics
    with_head = ["--model", str(checkpoints["seg"]), "--relpose-head", str(checkpoints["relpose"])]
    err = _error(
        capsys, ["localize", str(big), "--base", base, "--network-size", "none", *with_head]
    )
    assert "big.png" in err and "mismatched sizes" in err  # the features
    # ... or base images of different sizes
    _save(tmp_path / "base" / "img_2.png", np.zeros((96, 64, 3), np.uint8))
    err = _error(
        capsys,
        [
            "localize",
            str(q),
            "--base",
            base,
            *raw,
            "--model",
            str(checkpoints["seg"]),
            "--no-cache",
        ],
    )
    assert "mismatched sizes" in err and "base image img_2.png" in err


# ----------------------------------------------------------------------------- bad input


def _error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    return capsys.readouterr().err


def test_bad_inputs_exit_2_with_a_message(tmp_path: Path, capsys) -> None:
    images = random_base(tmp_path / "base")
    q = tmp_path / "q.png"
    _save(q, images[0])
    base = str(tmp_path / "base")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "empty image base" in _error(
        capsys, ["localize", *PLACEHOLDER, str(q), "--base", str(empty)]
    )
    # base images without poses
    orphan = tmp_path / "orphan"
    shutil.copytree(tmp_path / "base", orphan)
    _save(orphan / "stray.png", images[1])
    err = _error(capsys, ["localize", *PLACEHOLDER, str(q), "--base", str(orphan)])
    assert "without poses" in err and "stray.png" in err
    # GPS window without GPS, or a query missing from the GPS file
    assert "--gps" in _error(
        capsys, ["localize", *PLACEHOLDER, str(q), "--base", base, "--radius", "10"]
    )
    gps = tmp_path / "gps.csv"
    gps.write_text("image,x,y\nother.png,0,0\n")
    err = _error(
        capsys,
        ["localize", *PLACEHOLDER, str(q), "--base", base, "--gps", str(gps), "--radius", "5"],
    )
    assert "q.png" in err and "no row" in err
    assert "no such file" in _error(
        capsys,
        [
            "localize",
            *PLACEHOLDER,
            str(q),
            "--base",
            base,
            "--gps",
            str(tmp_path / "x.csv"),
            "--radius",
            "5",
        ],
    )
    # unreadable query, bad k, a head the chosen method does not use
    assert "missing.png" in _error(
        capsys, ["localize", *PLACEHOLDER, str(tmp_path / "missing.png"), "--base", base]
    )
    assert "--k" in _error(capsys, ["localize", *PLACEHOLDER, str(q), "--base", base, "--k", "0"])
    err = _error(
        capsys,
        [
            "localize",
            *PLACEHOLDER,
            str(q),
            "--base",
            base,
            "--relpose-head",
            str(tmp_path / "h.pt"),
        ],
    )
    assert "--relpose-head" in err and "not used" in err  # the essential matrix has no head
    err = _error(
        capsys, ["localize", str(q), "--base", base, "--relpose-head", str(tmp_path / "h.pt")]
    )
    assert "h.pt" in err  # the head is the default relative pose: a missing file is named
    assert "--radius" in _error(
        capsys,
        ["localize", *PLACEHOLDER, str(q), "--base", base, "--gps", str(gps), "--radius", "-1"],
    )
    # sequence options without --sequence, or out of range
    assert "--sequence" in _error(
        capsys, ["localize", *PLACEHOLDER, str(q), "--base", base, "--step-m", "5"]
    )
    assert "--step-m" in _error(
        capsys,
        [
            "localize",
            *PLACEHOLDER,
            str(q),
            "--base",
            base,
            "--sequence",
            "filter",
            "--step-m",
            "-5",
        ],
    )
    assert "--appearance-weight" in _error(
        capsys,
        [
            "localize",
            *PLACEHOLDER,
            str(q),
            "--base",
            base,
            "--sequence",
            "filter",
            "--appearance-weight",
            "1",
        ],
    )
    assert "--appearance-scale" in _error(
        capsys,
        [
            "localize",
            *PLACEHOLDER,
            str(q),
            "--base",
            base,
            "--sequence",
            "smooth",
            "--appearance-scale",
            "0",
        ],
    )

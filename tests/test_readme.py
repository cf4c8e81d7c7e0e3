"""The README's commands and Python snippets work as written, from a folder outside the repository.

Every ``bash`` and ``python`` block of README.md is run in document order in one temporary
folder (the inputs the "own data" walkthroughs name are made first, from a small render). The
commands run in this process through ``geoseg_cli.cli.main`` (what the ``geoseg`` entry point
calls), with their frame counts and image sizes capped (:data:`TINY`) to keep the suite short
(the demo excepted: it runs as a user runs it, and its figures are checked against
``bench/results/demo.json``, which the README's demo paragraph is written from). The walkthroughs'
localisations and SLAM run are checked in metres against the poses their renders wrote.
Installation, the test suite itself and training are not run (:data:`NOT_RUN`, with the reason);
a README command that is neither run nor listed there fails the test.
"""

from __future__ import annotations

import csv
import glob
import json
import re
import shlex
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from geoseg_cli.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PROVENANCE = ("command", "git_commit", "machine", "date", "split")  # bench/provenance.py's keys

# command prefix -> why the test does not run it
NOT_RUN = {
    "pip install": "installation (the test runs on the installed package)",
    "python -m pytest": "the test suite itself",
    "geoseg train": "training takes minutes to hours; tests/training runs each trainer on tiny configs",
    "python -m training.average": "it averages the runs trained above; tests/training/test_average.py",
}
# command -> option -> largest value the test uses (frames), or the value it uses (size); the
# demo keeps its defaults (~90 s), so that its figures are the ones the README quotes
TINY = {"render": {"--frames": 12}}
SIZES = {"render": "160x120"}
SLAM_FRAMES = 40  # the SLAM needs a few tens of frames to start: its render gets these
# the own-photos walkthrough localises copies of base images 1.1 m apart (measured: 1.12 and
# 0.07 m off, with the GPS fixes 1.41 m off and a 25 m window)
OWN_PHOTOS_MAX_ERROR_M = 2.0
# the winter frames localised as one drive against the summer base (measured: 0.10 and 0.09 m)
SEQUENCE_MAX_ERROR_M = 0.5
# the SLAM walkthrough's 40-frame drive (measured: 0.74 m horizontal, its GPS fixes 0.89 m)
SLAM_MAX_ERROR_M = 1.5
# the same drive from the winter base, no GPS (measured: 1.72 m; 8 fixes over its 4 s, each at
# a base image up to half the base's spacing away, where the GPS walkthrough has 40)
BASE_SLAM_MAX_ERROR_M = 2.5


def readme_blocks(text: str) -> list[tuple[str, str]]:
    """``(language, code)`` of the fenced ``bash`` and ``python`` blocks, in order."""
    return [
        (lang, code)
        for lang, code in re.findall(r"```(bash|python)\n(.*?)```", text, flags=re.DOTALL)
    ]


def bash_commands(code: str) -> list[str]:
    """The commands of a bash block: continuation lines joined, comments dropped, ``&&``
    chains split."""
    code = code.replace("\\\n", " ")
    out = []
    for line in code.splitlines():
        line = re.sub(r"\s+#.*$", "", line).strip()
        out += [c.strip() for c in line.split("&&") if c.strip()]
    return out


def _not_run(command: str) -> str | None:
    return next((why for prefix, why in NOT_RUN.items() if command.startswith(prefix)), None)


def _tiny(argv: list[str], slam_renders: set[str]) -> list[str]:
    """Cap frame counts and sizes (``argv`` without the leading ``geoseg``)."""
    name = argv[0]
    argv = list(argv)
    out_dir = argv[argv.index("--out") + 1] if "--out" in argv else None
    for option, cap in TINY.get(name, {}).items():
        if option in argv:
            i = argv.index(option) + 1
            argv[i] = str(min(int(argv[i]), cap))
        else:
            argv += [option, str(cap)]
    if name in SIZES:
        size = "320x240" if out_dir in slam_renders else SIZES[name]
        if "--size" in argv:
            argv[argv.index("--size") + 1] = size
        else:
            argv += ["--size", size]
    if name == "render" and out_dir in slam_renders:
        argv[argv.index("--frames") + 1] = str(SLAM_FRAMES)
    return argv


def _expand(argv: list[str]) -> list[str]:
    out = []
    for a in argv:
        hits = sorted(glob.glob(a)) if any(c in a for c in "*?[") else []
        out += hits or [a]
    return out


def _make_own_data(folder: Path) -> None:
    """The inputs the walkthroughs name: my_images/, my_photos/ + positions.csv, new_photos/,
    query_gps.csv (from a small render of the forward-looking car camera, whose
    heading is the track's, as the positions file assumes)."""
    src = folder / "_source"
    argv = ["render", "--out", str(src), "--frames", "8", "--rig", "car", "--size", "160x120"]
    assert main(argv) == 0
    import cv2

    with (src / "poses.csv").open() as f:
        poses = list(csv.DictReader(f))
    (folder / "my_images").mkdir()
    (folder / "my_photos").mkdir()
    (folder / "new_photos").mkdir()
    rows = ["image,x,y,z"]
    for i, pose in enumerate(poses):
        rgb = cv2.imread(str(src / "rgb" / f"{i:06d}.png"))
        cv2.imwrite(str(folder / "my_photos" / f"p{i:02d}.jpg"), rgb)
        rows.append(f"p{i:02d}.jpg,{pose['tx']},{pose['ty']},{float(pose['tz']) - 1.5}")
    (folder / "my_photos" / "positions.csv").write_text("\n".join(rows) + "\n")
    for name, i in (("street.jpg", 1), ("corner.jpg", 6)):
        shutil.copy(folder / "my_photos" / f"p{i:02d}.jpg", folder / "my_images" / name)
    gps = ["image,x,y"]
    for name, i in (("a.jpg", 2), ("b.jpg", 5)):
        shutil.copy(folder / "my_photos" / f"p{i:02d}.jpg", folder / "new_photos" / name)
        gps.append(f"{name},{float(poses[i]['tx']) + 1.0},{float(poses[i]['ty']) - 1.0}")
    (folder / "query_gps.csv").write_text("\n".join(gps) + "\n")


def test_readme_blocks_are_found() -> None:
    blocks = readme_blocks(README.read_text())
    commands = [c for lang, code in blocks if lang == "bash" for c in bash_commands(code)]
    assert "geoseg demo" in commands and "python -m pytest" in commands
    assert any(c.startswith("geoseg localize") for c in commands)
    assert sum(lang == "python" for lang, _ in blocks) >= 2


@pytest.mark.filterwarnings("ignore")
def test_every_readme_command_and_snippet_runs(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)  # not the repository: no configs/, no relative weights
    _make_own_data(tmp_path)
    blocks = readme_blocks(README.read_text())
    commands = [c for lang, code in blocks if lang == "bash" for c in bash_commands(code)]
    # renders whose output a `geoseg slam run` reads need the SLAM's frame count and size, and
    # so do the renders its image bases (--base) are built from
    slam_runs = [shlex.split(c) for c in commands if c.startswith("geoseg slam run")]
    slam_renders = {argv[3] for argv in slam_runs}
    bases = {argv[argv.index("--base") + 1] for argv in slam_runs if "--base" in argv}
    for c in commands:
        argv = shlex.split(c)
        if c.startswith("geoseg base build") and argv[argv.index("--out") + 1] in bases:
            slam_renders.add(argv[3])
    ran, skipped = [], []
    for lang, code in blocks:
        if lang == "python":
            exec(compile(code, "README.md", "exec"), {"__name__": "readme"})  # noqa: S102
            ran.append("python snippet")
            continue
        for command in bash_commands(code):
            if _not_run(command):
                skipped.append(command)
                continue
            argv = shlex.split(command)
            assert argv[0] == "geoseg", f"README command not run by this test: {command}"
            argv = _expand(_tiny(argv[1:], slam_renders))
            assert main(argv) == 0, f"README command failed: {command} (ran as {argv})"
            ran.append(command)
    out = capsys.readouterr().out
    # what the walkthroughs promise
    _check_demo_figures(out, tmp_path / "geoseg_demo" / "demo.json")
    _check_demo_outputs(out, tmp_path / "geoseg_demo")
    assert (tmp_path / "geoseg_demo" / "segmentation.png").is_file()
    assert (tmp_path / "my_labels" / "street_classes.png").is_file()
    assert (tmp_path / "my_labels" / "legend.json").is_file()
    _check_own_photos_localised(tmp_path)
    _check_sequence_localised(out, tmp_path)
    _check_slam(tmp_path / "drive_slam" / "summary.json")
    _check_slam_from_base(tmp_path / "drive_from_base" / "summary.json")
    assert len(ran) >= 12 and all(_not_run(c) for c in skipped)


def _check_demo_figures(out: str, figures_path: Path) -> None:
    """The demo prints the figures of its ``demo.json``, and they are the README's
    (``bench/results/demo.json``) within ``docs/make_results.py``'s ``DEMO_TOLERANCE``."""
    tol = _make_results().DEMO_TOLERANCE
    figures = json.loads(figures_path.read_text())
    quoted = json.loads((ROOT / "bench" / "results" / "demo.json").read_text())
    printed = re.search(r"segmentation \(.*?\): mIoU ([0-9.]+), pixel accuracy ([0-9.]+)", out)
    assert printed, "the demo's segmentation score is missing"
    assert float(printed[1]) == round(figures["segmentation_miou"], 3)
    assert float(printed[2]) == round(figures["segmentation_pixel_accuracy"], 3)
    assert set(figures) == {k for k in quoted if k not in PROVENANCE}, "demo.json's keys changed"
    for key, value in figures.items():
        if key.startswith("segmentation_"):
            allowed = tol["score"]
        elif key.startswith(("translation_error_m_", "gps_error_m_")):
            assert f"{value:.3f} m" in out or f"{value:.2f} m" in out, f"{key} not printed"
            allowed = max(tol["error_m"], tol["error_share"] * quoted[key])
        elif key.startswith("association_precision_"):
            allowed = tol["facade_share"]
        else:  # rotations, points on facades, failures: printed, not quoted with a tolerance
            continue
        assert abs(value - quoted[key]) <= allowed, f"demo {key} {value}, README {quoted[key]}"
    # what the figures say: with the true facades and no GPS, both building rules hold the
    # trajectory the SLAM alone lets drift
    for rule in ("raycast", "bayes"):
        error, alone = (
            figures[f"translation_error_m_{rule}_exact"],
            figures["translation_error_m_nobuild_exact"],
        )
        assert error < 0.5 * alone, f"{rule}: {error:.3f} m, without buildings {alone:.3f} m"


def _check_demo_outputs(out: str, demo: Path) -> None:
    """The buildings step prints each run in the README's words, with the experiment's names,
    and writes its report and pictures for both building models."""
    exact, gis = out.index("slam on images, exact"), out.index("slam on images, gis")
    assert exact < gis
    for block in (out[exact:gis], out[gis:]):
        for method, name in (("nobuild", "no buildings"), ("raycast", "geometric rule"),
                             ("bayes", "network")):  # fmt: skip
            assert f"  {name}" in block and f"({method})" in block
        assert "% on the right one" in block
    assert "GPS fixes" in out[gis:] and "GPS fixes" not in out[exact:gis]
    report = (demo / "buildings" / "buildings_ch4.md").read_text()
    assert "## Model `exact`" in report and "## Model `gis`" in report and "`bayes` |" in report
    for model in ("exact", "gis"):
        for name in ("trajectories", "association", "reprojection"):
            assert (demo / "buildings" / f"{name}_{model}.png").is_file()


def _check_own_photos_localised(folder: Path) -> None:
    """Each query photo (a copy of base image ``p02`` / ``p05``) finds its own base image first
    and is placed near its true position, in metres (not only inside the GPS window)."""
    with (folder / "_source" / "poses.csv").open() as f:
        poses = list(csv.DictReader(f))
    where = json.loads((folder / "where.json").read_text())
    copies = {"new_photos/a.jpg": 2, "new_photos/b.jpg": 5}
    assert sorted(q["image"] for q in where["queries"]) == sorted(copies)
    for query in where["queries"]:
        i = copies[query["image"]]
        assert query["matches"][0]["image"] == f"p{i:02d}.jpg", query["image"]
        truth = np.array([float(poses[i]["tx"]), float(poses[i]["ty"])])
        error = np.linalg.norm(np.array(query["position"]["xyz"])[:2] - truth)
        assert error < OWN_PHOTOS_MAX_ERROR_M, f"{query['image']}: {error:.2f} m from its pose"


def _check_sequence_localised(out: str, folder: Path) -> None:
    """The winter frames localised against the summer base as one drive land near the poses
    their render wrote."""
    with (folder / "winter" / "poses.csv").open() as f:
        poses = list(csv.DictReader(f))
    found = re.findall(
        r"^(\d{6})\.png .*?\n(?:.*\n)*?\s+position: x ([-0-9.]+)\s+y ([-0-9.]+)", out, re.M
    )
    assert [name for name, _, _ in found] == ["000005", "000010"], found
    for name, x, y in found:
        pose = poses[int(name)]
        error = np.hypot(float(x) - float(pose["tx"]), float(y) - float(pose["ty"]))
        assert error < SEQUENCE_MAX_ERROR_M, f"winter {name}: {error:.2f} m from its pose"


def _check_slam(summary_path: Path) -> None:
    """The SLAM walkthrough's run keeps its tracking and stays near the true poses."""
    summary = json.loads(summary_path.read_text())
    assert summary["status"] == "ok" and summary["georeferenced"], summary["status"]
    assert summary["tracking_failures"] == 0
    assert summary["translation_error_m"] < SLAM_MAX_ERROR_M, summary["translation_error_m"]


def _check_slam_from_base(summary_path: Path) -> None:
    """The run without GPS, from the winter base, is georeferenced by the base's fixes, which
    its keyframes log as theirs (no GPS's)."""
    summary = json.loads(summary_path.read_text())
    assert summary["georeferenced"] and summary["tracking_failures"] == 0, summary["status"]
    assert summary["base_fixes"] >= 0.8 * summary["base_frames_localised"] > 0
    assert summary["base_fused_keyframes"] > 0 and "gps_error_m" not in summary
    assert summary["base_adjustment"]["base_rows"] > 0  # the run closed on its fixes
    assert "online_translation_error_m" in summary
    assert summary["translation_error_m"] < BASE_SLAM_MAX_ERROR_M, summary["translation_error_m"]
    log = list(csv.DictReader(open(summary_path.parent / "keyframes.csv")))
    assert any("base" in r["constraints"] for r in log)
    assert not any("gps" in r["constraints"] for r in log)


def _make_results():
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_results", ROOT / "docs" / "make_results.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["make_results"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_results_page_and_readme_table_are_generated_from_bench_results() -> None:
    """docs/results.md and the README's table match bench/results/*.json (after a benchmark
    run: python docs/make_results.py)."""
    assert _make_results().main(["--check"]) == 0


def test_results_page_takes_unknown_and_broken_results_files(tmp_path: Path) -> None:
    mr = _make_results()
    (tmp_path / "new_bench.json").write_text(json.dumps({"speed": 2.5, "nested": {"a": 1}}))
    seg = {"miou": 0.5, "miou_std": 0.01, "machine": "m"}
    (tmp_path / "accuracy_seg.json").write_text(json.dumps(seg))
    (tmp_path / "broken.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    results = mr.load_results(tmp_path)
    assert set(results) == {"new_bench", "accuracy_seg"}
    page = mr.results_page(results)
    assert "## new_bench" in page and "| `nested.a` | 1 |" in page
    # a headline figure whose file is there; the others (files missing) are left out
    rows = mr.headline_rows(results)
    assert [r[1] for r in rows] == ["0.500 / 0.010"]
    # three significant digits, trailing zeros kept (0.630 is not 0.63); whole numbers plain
    assert [mr._num(v) for v in (0.63047, 0.0555, 17.6, 0.0, 3.0, 12345.6)] == [
        "0.630",
        "0.0555",
        "17.6",
        "0",
        "3",
        "12,346",
    ]
    readme = f"intro\n{mr.BEGIN}\nold table\n{mr.END}\nrest\n"
    new = mr.readme_with_table(readme, "NEW")
    assert new == f"intro\n{mr.BEGIN}\nNEW\n{mr.END}\nrest\n"

"""Every ``bench/results/*.json`` says where its figures come from, and the published tables are
generated from those files.

A bench writes its results file whole, with ``bench/provenance.py``'s keys: ``command``,
``git_commit`` (a committed checkout), ``machine``, ``date`` and ``split`` (which data: tuning,
report, a speed measurement...). Files written before the benches did so wait in
:data:`PENDING_REMEASURE`, each with the reason it was not re-measured yet; the list can only
shrink: a listed file that has its provenance, or no longer exists, fails the test.
"""

from __future__ import annotations

import datetime as dt
import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
PROVENANCE = ("command", "git_commit", "machine", "date", "split")

#: results file -> why it lacks its provenance and the command that re-measures it
PENDING_REMEASURE: dict[str, str] = {
    "accuracy_real.json": "fine-tunes two networks on CamVid train (hours of CPU): "
    "python bench/accuracy_real.py --full",
    "accuracy_real_naive.json": "the patch CNN's dense prediction takes ~1-3 s an image on "
    "the CPU: python bench/accuracy_real.py --model geoseg/weights/naive --tag naive "
    "--dirichlet dirichlet",
    "accuracy_real_naive_real.json": "its heldout_* figures were copied in from "
    "bench/accuracy_seg.py runs (no bench writes them into this file yet): python "
    "bench/accuracy_real.py --model geoseg/weights/naive_real --tag naive_real --dirichlet "
    "dirichlet_real --normals normals_real",
    "accuracy_real_seg_real.json": "its heldout_* figures were copied in from "
    "bench/accuracy_seg.py runs (no bench writes them into this file yet): python "
    "bench/accuracy_real.py --model geoseg/weights/seg_real --tag seg_real --normals "
    "normals_real",
    "accuracy_real_seg_real_train.json": "367 CamVid frames at two sizes, three colour "
    "variants: python bench/accuracy_real.py --model geoseg/weights/seg_real --tag seg_real "
    "--normals normals_real --split train",
    "ba_speed.json": "a timing ratio that moves with the host's load (ours / Ceres at C = 40: "
    "0.52 idle, 0.23-0.31 at load 6-10): re-measure on an idle host: python bench/ba_speed.py "
    "--repeat 5 (with the bench extra: gtsam, pycolmap)",
    "buildings_ch4.json": "assembled from several passes; to be re-measured on reporting "
    "drives (issue 58): python bench/buildings_ch4.py --full",
    "buildings_ch4_rerender.json": "a second render's run of bench/buildings_ch4.py, which "
    "writes only buildings_ch4.json: python bench/buildings_ch4.py --full --data OTHER_RENDER",
    "buildings_ch4_timing.json": "a subset of a bench/buildings_ch4.py run, which writes only "
    "buildings_ch4.json: python bench/buildings_ch4.py --full --data DRIVE --set "
    '"methods=[nobuild,bayes]" --set "models=[gis]" --set async_run=false',
    "fusion_ch3.json": "the chapter-3 grid on seven drives (tens of minutes): python "
    "bench/fusion_ch3.py --full --drives 3 4 6 7 8 9",
    "render_speed.json": "frames per second that a loaded host lowers (19.7 against 26.3 at "
    "320x240, load 5): re-measure on an idle host: python bench/render_speed.py",
    "train_speed.json": "thread settings timed against each other, ~10 min of both cores; "
    "re-measure with the host otherwise idle: python bench/train_speed.py",
}


def _missing(data: dict) -> list[str]:
    return [k for k in PROVENANCE if not (isinstance(data.get(k), str) and data[k].strip())]


def _load(path: Path) -> dict:
    data = json.loads(path.read_text())
    assert isinstance(data, dict), f"{path.name}: not a JSON object"
    return data


@pytest.mark.parametrize("path", sorted(RESULTS.glob("*.json")), ids=lambda p: p.name)
def test_results_file_says_where_its_figures_come_from(path: Path) -> None:
    data = _load(path)
    missing = _missing(data)
    if path.name in PENDING_REMEASURE:
        assert missing, f"{path.name} has its provenance now: remove it from PENDING_REMEASURE"
        return
    assert not missing, f"{path.name} lacks {missing}: re-run its bench (bench/provenance.py)"
    assert re.fullmatch(r"[0-9a-f]{40}", data["git_commit"]), (
        f"{path.name}: git_commit {data['git_commit']!r} is not a committed checkout"
    )
    date = dt.datetime.fromisoformat(data["date"])
    assert date.tzinfo is not None, f"{path.name}: date {data['date']!r} has no time zone"
    assert data["command"].startswith("python bench/"), f"{path.name}: {data['command']!r}"


def test_pending_list_only_names_files_that_exist() -> None:
    gone = sorted(name for name in PENDING_REMEASURE if not (RESULTS / name).is_file())
    assert not gone, f"no longer in bench/results: remove {gone} from PENDING_REMEASURE"


def _make_results():
    spec = importlib.util.spec_from_file_location("make_results", ROOT / "docs" / "make_results.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["make_results"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_results_page_and_readme_table_are_what_the_generator_writes() -> None:
    mr = _make_results()
    results = mr.load_results(RESULTS)
    assert set(results) == {p.stem for p in RESULTS.glob("*.json")}, "a results file is unread"
    page = (ROOT / "docs" / "results.md").read_text()
    assert page == mr.results_page(results), "docs/results.md: run python docs/make_results.py"
    readme = (ROOT / "README.md").read_text()
    table = mr.headline_table(results, "docs/results.md")
    assert readme == mr.readme_with_table(readme, table), (
        "README.md's results table: run python docs/make_results.py"
    )
    demo = mr.demo_paragraph(results)
    assert readme == mr.readme_with_table(readme, demo, mr.DEMO_BEGIN, mr.DEMO_END), (
        "README.md's demo figures: run python docs/make_results.py"
    )


def test_every_results_file_is_described_and_every_other_entry_is_used() -> None:
    """A results file that no page describes, or a picture or folder that no document names,
    is an experiment's leftover: history belongs to git."""
    mr = _make_results()
    undescribed = sorted(p.name for p in RESULTS.glob("*.json") if p.stem not in mr.ABOUT)
    assert not undescribed, f"add a line to docs/make_results.py's ABOUT or remove {undescribed}"
    texts = [ROOT / "README.md", ROOT / "docs" / "make_results.py"]
    texts += sorted((ROOT / "docs").glob("*.md")) + sorted((ROOT / "tests").rglob("*.py"))
    corpus = "\n".join(t.read_text() for t in texts)
    unused = sorted(
        p.name for p in RESULTS.iterdir() if p.suffix != ".json" and p.name not in corpus
    )
    assert not unused, f"named by no document or test: {unused}"

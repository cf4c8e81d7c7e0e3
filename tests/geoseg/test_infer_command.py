"""`geoseg infer` over batches: unique outputs per input, every unreadable input reported."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geoseg.errors import GeosegError
from geoseg_cli.cli import main
from geoseg_cli.commands.infer import output_stems


@pytest.fixture(scope="module")
def model(enet_files):
    return enet_files[1]


def _image(path, value: int, size=(24, 32)):
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.random.default_rng(value).integers(0, 256, (*size, 3), dtype=np.uint8)
    cv2.imwrite(str(path), img)
    return path


def test_same_names_in_two_folders_give_two_results(model, tmp_path) -> None:
    a = _image(tmp_path / "in" / "a" / "x.png", 1)
    b = _image(tmp_path / "in" / "b" / "x.png", 2)
    out = tmp_path / "out"
    assert main(["infer", str(a), str(b), "--model", str(model), "--out", str(out)]) == 0
    la, lb = (cv2.imread(str(out / d / "x_overlay.png")) for d in ("a", "b"))
    assert la is not None and lb is not None and not np.array_equal(la, lb)


def test_one_folder_keeps_flat_names_and_colliding_stems_are_refused(tmp_path) -> None:
    a, b = tmp_path / "x.png", tmp_path / "y.png"
    assert output_stems([a, b]) == {a: "x", b: "y"}
    assert output_stems([a, a]) == {a: "x"}
    with pytest.raises(GeosegError, match="x.png and .*x.jpg would both write"):
        output_stems([a, tmp_path / "x.jpg"])


def test_a_batch_reports_every_unreadable_input_and_goes_on(model, tmp_path, capsys) -> None:
    good1 = _image(tmp_path / "good1.png", 1)
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    missing = tmp_path / "missing.png"
    tiny = _image(tmp_path / "tiny.png", 3, size=(1, 1))
    good2 = _image(tmp_path / "good2.png", 4)
    out = tmp_path / "out"
    argv = ["infer", str(good1), str(broken), str(missing), str(tiny), str(good2)]
    assert main(argv + ["--model", str(model), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "3 of 5 input(s)" in err
    for name in ("broken.png", "missing.png", "tiny.png"):
        assert name in err
    assert (out / "good1_labels.png").is_file() and (out / "good2_labels.png").is_file()


def test_a_wrong_path_is_named_plainly_and_leaves_nothing(model, tmp_path, capfd) -> None:
    """Only missing inputs: a message before any work and no output folder; a missing and a
    broken input: no raw OpenCV warning, and the message does not claim that others were
    written."""
    out = tmp_path / "out"
    argv = ["infer", str(tmp_path / "typo.png"), "--model", str(model), "--out", str(out)]
    assert main(argv) == 2
    err = capfd.readouterr().err
    assert "none of the 1 input(s) exists" in err and "typo.png" in err and not out.exists()
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    argv = ["infer", str(tmp_path / "typo.png"), str(broken), "--model", str(model)]
    assert main(argv + ["--out", str(out)]) == 2
    err = capfd.readouterr().err
    assert "WARN" not in err and "others were written" not in err and "only the legend" in err
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "legend.json",
        "legend.png",
    ]


def test_infer_refuses_a_folder_of_other_files_and_a_file_as_out(model, tmp_path, capsys) -> None:
    image = _image(tmp_path / "in" / "x.png", 1)
    other = tmp_path / "other"
    other.mkdir()
    (other / "thesis.pdf").write_bytes(b"%PDF")
    assert main(["infer", str(image), "--model", str(model), "--out", str(other)]) == 2
    assert "thesis.pdf" in capsys.readouterr().err
    assert sorted(p.name for p in other.iterdir()) == ["thesis.pdf"]
    assert (
        main(["infer", str(image), "--model", str(model), "--out", str(other), "--overwrite"]) == 0
    )
    assert (other / "thesis.pdf").read_bytes() == b"%PDF"
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["infer", str(image), "--model", str(model), "--out", str(blocker)]) == 2
    assert "is a file" in capsys.readouterr().err


def test_outputs_class_ids_colours_masked_normals_and_probabilities(tmp_path) -> None:
    import json

    from geoseg.classes import PALETTE, SKY

    image = _image(tmp_path / "street.png", 5, size=(48, 64))
    out = tmp_path / "out"
    assert main(["infer", str(image), "--out", str(out), "--probabilities"]) == 0  # shipped net
    classes = cv2.imread(str(out / "street_classes.png"), cv2.IMREAD_UNCHANGED)
    assert classes.dtype == np.uint8 and classes.shape == (48, 64) and classes.max() < 8
    colours = cv2.cvtColor(cv2.imread(str(out / "street_labels.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(colours, PALETTE[classes])
    probs = np.load(out / "street_probabilities.npy")
    assert probs.shape == (8, 48, 64) and probs.dtype == np.float16
    np.testing.assert_array_equal(probs.astype(np.float32).argmax(0) == classes, True)
    normals = np.load(out / "street_normals.npy")
    invalid = np.isnan(normals).any(axis=0)
    np.testing.assert_array_equal(invalid, classes == SKY)
    np.testing.assert_allclose(np.linalg.norm(normals[:, ~invalid], axis=0), 1.0, atol=1e-3)
    legend = json.loads((out / "legend.json").read_text())
    assert [c["name"] for c in legend["classes"]][SKY] == "sky" and len(legend["classes"]) == 8
    key = cv2.imread(str(out / "legend.png"))
    assert key.shape == (240, 560, 3)  # the class colours beside the normal-colour sphere


def test_normals_are_masked_on_the_sky() -> None:
    from geoseg.classes import BUILDING, SKY
    from geoseg_cli.commands.infer import masked_normals

    normals = np.zeros((3, 2, 2), np.float32)
    normals[2] = -1.0
    labels = np.array([[SKY, BUILDING], [BUILDING, SKY]])
    got = masked_normals(normals, labels)
    assert np.isnan(got[:, 0, 0]).all() and np.isnan(got[:, 1, 1]).all()
    np.testing.assert_array_equal(got[:, 0, 1], [0, 0, -1])
    assert not np.isnan(normals).any()  # the input is left as it was


def test_colour_transfer_option_reads_the_model_card(model, tmp_path, capsys) -> None:
    import json
    import shutil

    from geoseg.colour_transfer import CARD_KEY, ColourStatistics

    image = _image(tmp_path / "in" / "x.png", 5)
    bare = tmp_path / "bare" / model.name
    bare.parent.mkdir()
    shutil.copy(model, bare)
    argv = ["infer", str(image), "--model", str(bare), "--colour-transfer", "image"]
    assert main(argv + ["--out", str(tmp_path / "o1")]) == 2
    assert "no model card" in capsys.readouterr().err
    dark_green = ColourStatistics(mean=(-2.0, -0.3, -0.1), std=(0.1, 0.01, 0.01))
    (bare.parent / "model_card.json").write_text(json.dumps({CARD_KEY: dark_green.as_dict()}))
    for mode, out in (("off", "plain"), ("image", "image"), ("sequence", "seq")):
        argv = ["infer", str(image), "--model", str(bare), "--colour-transfer", mode]
        assert main(argv + ["--out", str(tmp_path / out)]) == 0
    labels = {o: cv2.imread(str(tmp_path / o / "x_labels.png")) for o in ("plain", "image", "seq")}
    assert not np.array_equal(labels["plain"], labels["image"])
    # one input: its own statistics are the sequence's
    assert np.array_equal(labels["image"], labels["seq"])


def test_model_by_shipped_name_is_those_weights(tmp_path) -> None:
    from geoseg.infer import Segmenter
    from geoseg.pretrained import pretrained_file

    image = _image(tmp_path / "street.png", 7, size=(48, 64))
    assert main(["infer", str(image), "--model", "seg", "--out", str(tmp_path / "a")]) == 0
    classes = cv2.imread(str(tmp_path / "a" / "street_classes.png"), cv2.IMREAD_UNCHANGED)
    seg = Segmenter.from_onnx(pretrained_file("seg", "model.onnx"))
    expected = seg(cv2.cvtColor(cv2.imread(str(image)), cv2.COLOR_BGR2RGB)).labels[0]
    np.testing.assert_array_equal(classes, expected)
    assert not (tmp_path / "a" / "street_normals.npy").exists()  # labels-only weights
    missing = tmp_path / "no_such_model.onnx"
    assert main(["infer", str(image), "--model", str(missing), "--out", str(tmp_path / "b")]) == 2

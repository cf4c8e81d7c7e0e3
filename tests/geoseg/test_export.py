"""ONNX export: torch vs onnxruntime parity on a second input size for every exported model.

The export rewrites themselves (torch against torch) are tested in test_export_rewrites.py.

Export is slow (20-40 s per ENet-sized model on 2 CPU cores): every model is exported once per
session, at 64x48, and compared at 37x50 (sides not multiples of 8) with batch 2. The exports are
shared (``exported_model`` and ``joint_files`` in tests/conftest.py): the joint model is the one
`geoseg export --checkpoint` wrote, with non-default batch-norm statistics.
"""

import numpy as np
import pytest
import torch

from geoseg.errors import GeosegError
from geoseg.export import OnnxModel, default_example_inputs, export_onnx, prepare_for_export
from geoseg.infer import load_model_checkpoint
from geoseg.models import get_model, list_models

H2, W2 = 37, 50  # the second size


def _export(name: str, exported_model, joint_files):
    """``(reference, onnx_model)``: the torch model to compare with and its ONNX session."""
    if name == "joint":
        model, path = load_model_checkpoint(joint_files[0])[0], joint_files[1]
    else:
        model, path = exported_model(name)
    # the reference is the model itself (its PReLUs included); the naive CNN runs densely
    reference = prepare_for_export(model).eval() if name == "naive_cnn" else model
    return reference, OnnxModel(path, providers=["CPUExecutionProvider"])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1.0, 1.0)))


def test_registry_lists_every_model_and_rejects_unknown() -> None:
    assert list_models() == ["enet", "joint", "naive_cnn", "reloc", "relpose"]
    with pytest.raises(GeosegError, match="known models: enet, joint"):
        get_model("resnet")
    with pytest.raises(GeosegError, match="unknown option"):
        get_model("enet", width=3)


@pytest.mark.slow  # the ENet and joint exports (shared, tests/conftest.py)
@pytest.mark.parametrize("name", ["enet", "joint", "naive_cnn"])
def test_image_models_parity_on_a_second_size(name: str, exported_model, joint_files) -> None:
    model, onnx_model = _export(name, exported_model, joint_files)
    assert onnx_model.metadata["model_name"] == name
    assert onnx_model.metadata["dynamic_spatial"] is True
    x = torch.randn(2, 3, H2, W2, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        ref = {k: v.numpy() for k, v in model(x).items()}
    got = onnx_model(x.numpy())
    assert set(got) == set(ref) and onnx_model.output_names == list(ref)
    for key in ref:
        assert got[key].shape == ref[key].shape, key
    scores = "log_probs" if name == "naive_cnn" else "logits"
    agreement = (got[scores].argmax(1) == ref[scores].argmax(1)).mean()
    assert agreement >= 0.999
    if "normals" in ref:
        assert _angle_deg(got["normals"], ref["normals"]).mean() <= 0.5
    if "features" in ref:
        assert np.abs(got["features"] - ref["features"]).mean() <= 1e-4 * (
            1 + np.abs(ref["features"]).mean()
        )
    tensors = onnx_model(x)  # tensors in → tensors out
    assert isinstance(tensors[scores], torch.Tensor)


@pytest.mark.slow  # the joint export (shared, tests/conftest.py)
def test_joint_labels_identical_on_flat_regions(joint_files) -> None:
    """Flat image regions tie every 2x2 pooling window of the encoder: the exported switch masks
    must mark torch's index there (the first maximum), or unpooling spreads the decoder's values
    over whole windows and the labels change."""
    model, onnx_model = _export("joint", None, joint_files)
    x = torch.randn(1, 3, 48, 64, generator=torch.Generator().manual_seed(5))
    x[..., :24, :32] = 0.3
    x[..., 24:, 32:] = -1.0
    with torch.no_grad():
        ref = {k: v.numpy() for k, v in model(x).items()}
    got = onnx_model(x.numpy())
    top2 = np.sort(ref["logits"], axis=1)[:, -2:]
    clear = top2[:, 1] - top2[:, 0] > 1e-3  # not a near-tie of two classes
    assert clear.mean() > 0.99
    labels, want = got["logits"].argmax(1), ref["logits"].argmax(1)
    np.testing.assert_array_equal(labels[clear], want[clear])
    angles = _angle_deg(got["normals"], ref["normals"])
    assert angles.mean() <= 0.05 and np.percentile(angles, 99) <= 0.5


def test_reloc_head_parity(exported_model) -> None:
    model, onnx_model = _export("reloc", exported_model, None)
    feat = torch.randn(3, 128, 5, 7, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        ref = model(feat)["embedding"].numpy()
    got = onnx_model(feat.numpy())["embedding"]
    cos = (got * ref).sum(1) / (np.linalg.norm(got, axis=1) * np.linalg.norm(ref, axis=1))
    assert got.shape == ref.shape and cos.min() >= 0.9999


def test_relpose_head_parity(exported_model) -> None:
    model, onnx_model = _export("relpose", exported_model, None)
    gen = torch.Generator().manual_seed(3)
    a, b = (torch.randn(3, 128, 5, 7, generator=gen) for _ in range(2))
    with torch.no_grad():
        ref = {k: v.numpy() for k, v in model(a, b).items()}
    got = onnx_model(a.numpy(), b.numpy())
    for key in ("rotation", "direction"):
        assert got[key].shape == ref[key].shape == (3, 3)
        np.testing.assert_allclose(got[key], ref[key], atol=1e-4, rtol=1e-3)


def test_enet_is_exported_in_its_rewritten_form(exported_model, tmp_path) -> None:
    import onnx

    model, rewritten_path = exported_model("enet")  # export_onnx's default: rewrite=True
    prepared = prepare_for_export(model)
    assert prepared is not model  # a copy: the user's model keeps its modules
    assert any(isinstance(m, torch.nn.PReLU) for m in model.modules())
    assert not any(isinstance(m, torch.nn.PReLU) for m in prepared.modules())
    assert prepare_for_export(model, rewrite=False) is model
    rewritten = {n.op_type for n in onnx.load(str(rewritten_path)).graph.node}
    plain = {
        n.op_type
        for n in onnx.load(str(export_onnx(model, tmp_path / "b.onnx", rewrite=False))).graph.node
    }
    assert {"PRelu", "ScatterND"} <= plain
    assert not rewritten & {"PRelu", "ScatterND", "MaxUnpool"}
    # pixel shuffles run as Col2Im (DepthToSpace is slow in onnxruntime)
    assert "DepthToSpace" not in rewritten
    shuffles = [n for n in onnx.load(str(rewritten_path)).graph.node if n.op_type == "Col2Im"]
    # two sub-pixel transposed convolutions and the last 2x2 transposed conv (the switch masks
    # are computed at full resolution, without a shuffle)
    assert len(shuffles) == 3
    assert not rewritten & {"ConvTranspose", "ArgMax"}


def test_switch_mask_keeps_torchs_tie_rule_in_onnxruntime(tmp_path) -> None:
    from geoseg.export_rewrites import switch_mask

    class Mask(torch.nn.Module):
        def forward(self, x):
            return {"mask": switch_mask(x)[1]}

    # small integers: most 2x2 windows hold ties, where only the first maximum may be marked
    gen = torch.Generator().manual_seed(4)
    x = torch.randint(0, 3, (2, 16, 12, 18), generator=gen).float()
    path = export_onnx(Mask(), tmp_path / "mask.onnx", example_inputs=torch.zeros(1, 16, 8, 8))
    got = OnnxModel(path, providers=["CPUExecutionProvider"])(x.numpy())["mask"]
    pooled, indices = torch.nn.functional.max_pool2d(x, 2, 2, return_indices=True)
    expected = torch.nn.functional.max_unpool2d(
        torch.ones_like(pooled), indices, 2, 2, output_size=x.shape[-2:]
    )
    np.testing.assert_array_equal(got, expected.numpy())


def test_default_example_inputs_for_heads() -> None:
    class Head(torch.nn.Module):
        def forward(self, a, b):
            return {"d": a - b}

    inputs = default_example_inputs(Head(), height=64, width=48)
    assert len(inputs) == 2 and inputs[0].shape == (1, 128, 8, 6)


def test_corrupt_and_missing_onnx_files_name_the_file(tmp_path) -> None:
    bad = tmp_path / "broken.onnx"
    bad.write_bytes(b"this is not a protobuf")
    with pytest.raises(GeosegError, match="broken.onnx"):
        OnnxModel(bad)
    with pytest.raises(GeosegError, match="nothere.onnx"):
        OnnxModel(tmp_path / "nothere.onnx")


def test_onnx_input_validation(exported_model) -> None:
    _, path = exported_model("naive_cnn")
    m = OnnxModel(path)
    with pytest.raises(GeosegError, match="naive_cnn.onnx.*size 3"):
        m(np.zeros((1, 4, 8, 8), np.float32))
    with pytest.raises(GeosegError, match="4-D"):
        m(np.zeros((8, 8), np.float32))
    with pytest.raises(GeosegError, match="float32"):
        m(np.zeros((1, 3, 8, 8), np.uint8))
    with pytest.raises(GeosegError, match="NaN"):
        m(np.full((1, 3, 8, 8), np.nan, np.float32))
    with pytest.raises(GeosegError, match="1 input"):
        m(np.zeros((1, 3, 8, 8), np.float32), np.zeros((1, 3, 8, 8), np.float32))


def test_onnx_session_fixed_dims(exported_model) -> None:
    _, path = exported_model("naive_cnn")
    x = np.random.default_rng(0).standard_normal((2, 3, 9, 11)).astype(np.float32)
    fixed = OnnxModel(path, fixed_dims={"batch": 2, "height": 9, "width": 11})
    assert fixed.session.get_inputs()[0].shape == [2, 3, 9, 11]
    np.testing.assert_allclose(fixed(x)["log_probs"], OnnxModel(path)(x)["log_probs"], atol=1e-5)
    with pytest.raises(GeosegError, match="size 9 in dim 2"):
        fixed(x[:, :, :8])
    with pytest.raises(GeosegError, match=r"\['hieght'\] are not symbolic.*'height'"):
        OnnxModel(path, fixed_dims={"hieght": 9})
    for bad in (0, 2.5, True):
        with pytest.raises(GeosegError, match="positive int"):
            OnnxModel(path, fixed_dims={"height": bad})
    with pytest.raises(GeosegError, match="'auto' or None"):
        OnnxModel(path, fixed_dims="fixed")


def test_onnx_auto_fixed_sessions_per_shape(exported_model) -> None:
    _, path = exported_model("naive_cnn")
    dynamic, auto = OnnxModel(path), OnnxModel(path, fixed_dims="auto")
    rng = np.random.default_rng(1)
    shapes = [
        (1, 3, 9, 11),
        (2, 3, 9, 11),
        (1, 3, 9, 11),
        (1, 3, 12, 8),
        (1, 3, 5, 5),
        (1, 3, 6, 7),
    ]
    for shape in shapes:
        x = rng.standard_normal(shape).astype(np.float32)
        got = auto(x)["log_probs"]
        np.testing.assert_allclose(got, dynamic(x)["log_probs"], atol=1e-5)
    # one session per distinct shape, up to the cap; the fifth shape ran on the dynamic session
    fixed = auto._fixed_sessions
    assert len(fixed) == OnnxModel.MAX_FIXED_SESSIONS == 4
    assert fixed[((1, 3, 9, 11),)].get_inputs()[0].shape == [1, 3, 9, 11]
    assert ((1, 3, 6, 7),) not in fixed
    with pytest.raises(GeosegError, match="size 3 in dim 1"):  # still validated
        auto(np.zeros((1, 4, 9, 11), np.float32))

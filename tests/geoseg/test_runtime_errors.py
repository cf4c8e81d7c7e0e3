"""Failures of the machine, not of the input (no CUDA, an allocator that gives up, a read-only
folder, a missing execution provider): each is a clear error naming the cause, not a traceback
from deep inside torch or onnxruntime, nor a silent fallback."""

from __future__ import annotations

import errno

import numpy as np
import pytest
import torch

from geoseg.errors import GeosegError, OutputError
from geoseg.export import OnnxModel
from geoseg.infer import Segmenter, load_model_checkpoint
from geoseg.output_dir import prepare_output_dir


@pytest.fixture(scope="module")
def files(enet_files):
    return enet_files


def test_cuda_asked_for_without_cuda_is_said_so(files, monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(GeosegError, match="CUDA is not available") as info:
        load_model_checkpoint(files[0], map_location="cuda")
    assert "checkpoint" not in str(info.value) and "corrupt" not in str(info.value)


def test_an_allocator_failure_names_the_image_size(files, monkeypatch) -> None:
    seg = Segmenter.from_checkpoint(files[0])
    from geoseg.models.enet import ENet

    def out_of_memory(self, x):
        raise RuntimeError(
            "[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: can't allocate"
        )

    monkeypatch.setattr(ENet, "forward", out_of_memory)
    with pytest.raises(GeosegError, match=r"enet.pt: .*1 image\(s\) of 40x24 pixels.*ONNX"):
        seg(np.zeros((24, 40, 3), np.uint8))


def test_onnxruntime_providers_and_threads_are_checked(files) -> None:
    onnx_path = files[1]
    with pytest.raises(GeosegError, match="unknown onnxruntime execution provider 'GPUProvider'"):
        OnnxModel(onnx_path, providers=["GPUProvider"])
    import onnxruntime as ort

    missing = [p for p in ort.get_all_providers() if p not in ort.get_available_providers()]
    with pytest.raises(GeosegError, match="not available in this onnxruntime"):
        OnnxModel(onnx_path, providers=[missing[0]])
    for threads in (-3, 0, 2.5, True):
        with pytest.raises(GeosegError, match="threads"):
            OnnxModel(onnx_path, providers=["CPUExecutionProvider"], threads=threads)
    assert OnnxModel(onnx_path, providers=["CPUExecutionProvider"], threads=1).providers == [
        "CPUExecutionProvider"
    ]


def test_a_read_only_output_folder_is_said_so(tmp_path, monkeypatch) -> None:
    import tempfile

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(tempfile, "NamedTemporaryFile", refuse)  # root ignores chmod
    with pytest.raises(OutputError, match="--out: .*not writable: Permission denied"):
        prepare_output_dir(tmp_path / "out", producer="infer")

"""DDP with 2 CPU processes (torchrun, gloo) gives the same weights as 1 process on the same
global batch."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from geoseg.errors import GeosegError
from training.distributed import (
    all_reduce_mean,
    find_free_port,
    get_world_size,
    init_distributed,
    is_main_process,
    make_sampler,
    resolve_device,
)

# Shared by the torchrun workers and the single-process reference run.
COMMON = textwrap.dedent(
    """
    import sys
    from pathlib import Path

    import torch
    from torch import nn
    from torch.utils.data import Dataset

    from geoseg.config import load_config
    from training.config import TrainConfig
    from training.distributed import make_loader
    from training.loop import fit
    from training.metrics import SegmentationMeter


    class Net(nn.Module):  # no batch norm, no dropout: DDP must match exactly
        def __init__(self):
            super().__init__()
            self.conv = nn.Conv2d(3, 6, 3, padding=1)
            self.head = nn.Conv2d(6, 3, 1)

        def forward(self, x):
            return {"logits": self.head(torch.tanh(self.conv(x)))}


    class Frames(Dataset):
        def __init__(self, n, seed):
            g = torch.Generator().manual_seed(seed)
            self.images = torch.rand(n, 3, 6, 6, generator=g)
            self.labels = (self.images[:, 1] * 3).long().clamp(max=2)

        def __len__(self):
            return len(self.images)

        def __getitem__(self, i):
            return {"image": self.images[i], "labels": self.labels[i]}


    def loss_fn(outputs, batch):
        return nn.functional.cross_entropy(outputs["logits"], batch["labels"])


    def run(out_dir, batch_size):
        cfg = load_config(
            TrainConfig,
            {"model": "net", "epochs": 2, "batch_size": batch_size, "device": "cpu",
             "out_dir": str(out_dir), "progress": False, "plots": False, "optim": {"lr": 0.01}},
        )
        torch.manual_seed(0)
        model = Net()
        train = make_loader(Frames(16, 0), batch_size=batch_size, shuffle=False)
        val = make_loader(Frames(4, 1), batch_size=2, shuffle=False)
        return fit(cfg, model, train, val, loss_fn, SegmentationMeter(3, class_names="abc"))
    """
)

WORKER = COMMON + textwrap.dedent(
    """
    if __name__ == "__main__":
        from training.distributed import cleanup, get_world_size, init_distributed

        info = init_distributed("cpu")
        assert info.distributed and get_world_size() == 2 and info.backend == "gloo"
        run(Path(sys.argv[1]), batch_size=4)  # 2 processes x 4 = global batch 8
        cleanup()
    """
)


def test_single_process_fallbacks() -> None:
    assert get_world_size() == 1 and is_main_process()
    assert all_reduce_mean({"a": 2.0}, weight=3) == {"a": 2.0}
    info = init_distributed("cpu")
    assert not info.distributed and info.is_main
    assert type(make_sampler(list(range(4)), shuffle=True)).__name__ == "RandomSampler"
    if not torch.cuda.is_available():
        assert resolve_device("auto") == torch.device("cpu")
        with pytest.raises(GeosegError, match="CUDA is not available"):
            resolve_device("cuda")


@pytest.mark.slow
def test_ddp_two_cpu_processes_match_one_process(tmp_path: Path) -> None:
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nnodes=1", "--nproc_per_node=2",
        "--master_addr=127.0.0.1", f"--master_port={find_free_port()}",
        str(script), str(tmp_path / "ddp"),
    ]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]

    namespace: dict = {}
    exec(compile(COMMON, "common", "exec"), namespace)
    single = namespace["run"](tmp_path / "single", batch_size=8)

    ddp = torch.load(tmp_path / "ddp" / "last.pt", weights_only=True)
    one = torch.load(single / "last.pt", weights_only=True)
    assert ddp["global_step"] == one["global_step"] == 4
    for key, value in one["model"].items():
        assert torch.allclose(value, ddp["model"][key], atol=1e-5, rtol=1e-4), key
    start = {k: v for k, v in namespace["Net"]().state_dict().items()}
    assert any(not torch.allclose(start[k], v) for k, v in one["model"].items())  # it trained
    h_ddp, h_one = ddp["history"][-1], one["history"][-1]
    assert h_ddp["train_loss"] == pytest.approx(h_one["train_loss"], rel=1e-4)
    assert h_ddp["val_loss"] == pytest.approx(h_one["val_loss"], rel=1e-4)
    assert h_ddp["val_miou"] == pytest.approx(h_one["val_miou"], abs=1e-9)

"""The harness of the bad-input suite: an environment of good and bad files, the cases' argv
builders, the stubs that stand for expensive work, and the classifier.

A case runs ``geoseg_cli.cli.main`` in-process and is classified:

* **A** clear error: exit status 2 with ``error:`` and the expected words (the option or file) on
  stderr, or argparse's usage error;
* **B** traceback: any exception escaping ``main``;
* **C** silent wrong result: exit 0 (or the command reaching its real work) on a bad input;
* **D** data loss: a file that existed before the command (inputs, a user's files next to or in
  the output) changed or vanished; files a command recorded writing (its own outputs) may be
  rewritten.

Expensive work is replaced by stubs that raise :class:`Accepted` once a command has validated
everything and starts working (rendering frames, training epochs, the ONNX exporter, bench
scripts): reaching a stub on a bad input is a C. :data:`OUTCOMES` (table cases) and
:data:`GENERATED` (generated bad values) count the outcomes per command; ``conftest.py`` prints
them at the end of the session.
"""

from __future__ import annotations

import hashlib
import json
import runpy
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from geoseg.dirichlet import DirichletFilter
from geoseg.export import export_onnx
from geoseg.infer import save_model_checkpoint
from geoseg.models import get_model
from geoseg.reloc.image_base import write_poses_csv
from geoseg_cli.cli import main

R_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
OUTCOMES: dict[str, Counter] = defaultdict(Counter)  # table cases, per command
GENERATED: dict[str, Counter] = defaultdict(Counter)  # generated bad values, per command
# slam-eval is being rewritten (slam_bridge/experiments); its own tests cover its inputs.
COVERED = ("render", "demo", "train", "export", "infer", "base", "localize", "slam", "bench")
REPORTED = (*COVERED, "python API")


class Accepted(Exception):
    """Raised by the stubs where a command starts its real work: everything was accepted."""


def _accept(*args, **kwargs):
    raise Accepted


# ============================================================================ the environment


@dataclass
class Env:
    root: Path
    inputs: Path
    world: Path
    onnx: Path
    pt: Path
    reloc_onnx: Path
    image: Path
    base: Path
    cache: Path

    def out(self, name: str = "out") -> Path:
        return self.root / "outs" / name


def _png(path: Path, hw=(48, 64), seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (*hw, 3), dtype=np.uint8), (5, 5), 0)
    cv2.imwrite(str(path), img)
    return path


def build_env(root: Path, enet_files: tuple[Path, Path]) -> Env:
    """The inputs every case draws from (good and bad files), under ``root``."""
    import shutil

    from geoseg.infer import load_model_checkpoint

    inputs = root / "inputs"
    inputs.mkdir()
    world = inputs / "world_tiny.yaml"
    world.write_text("seed: 4\npreset: light\nblocks_x: 1\nblocks_y: 1\n")
    pt = Path(shutil.copyfile(enet_files[0], inputs / "enet.pt"))
    onnx_path = Path(shutil.copyfile(enet_files[1], inputs / "enet.onnx"))
    enet, _ = load_model_checkpoint(pt)
    torch.manual_seed(0)
    reloc = get_model("reloc").eval()
    reloc_onnx = export_onnx(reloc, inputs / "reloc.onnx", metadata={"model_name": "reloc"})
    base = inputs / "base"
    names = []
    for i in range(3):
        _png(base / f"img_{i}.png", seed=i)
        names.append(f"img_{i}.png")
    t = np.c_[np.arange(3) * 10.0, np.zeros(3), np.full(3, 1.5)]
    write_poses_csv(base / "poses.csv", names, np.stack([R_NORTH] * 3), t)
    camera = {"K": [[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]], "image_size": [64, 48]}
    (base / "camera.json").write_text(json.dumps(camera))
    # bad files, next to the good ones
    (inputs / "text.pt").write_text("these are not weights\n")
    (inputs / "garbage.png").write_bytes(b"\x89PNG but not really")
    (inputs / "empty.png").write_bytes(b"")
    _png(inputs / "tiny.png", hw=(1, 1))
    _png(inputs / "big.png", hw=(96, 128), seed=1)
    data = bytearray(pt.read_bytes())
    for i in range(len(data) // 2, len(data) // 2 + 64):
        data[i] ^= 0xFF
    (inputs / "corrupt.pt").write_bytes(bytes(data))
    data = bytearray(onnx_path.read_bytes())
    for i in range(len(data) // 2, len(data) // 2 + 64):
        data[i] ^= 0xFF
    (inputs / "corrupt.onnx").write_bytes(bytes(data))
    torch.save(enet.state_dict(), inputs / "bare_state.pt")
    nan = get_model("enet", num_classes=8).eval()
    with torch.no_grad():
        for p in nan.parameters():
            p.fill_(float("nan"))
    save_model_checkpoint(nan, inputs / "nan.pt", model_name="enet", model_config={})
    (inputs / "gps.csv").write_text("image,x,y\nimg_1.png,10.0,0.5\n")
    (inputs / "gps_nan.csv").write_text("image,x,y\nimg_1.png,nan,0.5\n")
    (inputs / "gps_cols.csv").write_text("name,east,north\nimg_1.png,10.0,0.5\n")
    (inputs / "gps_other.csv").write_text("image,x,y\nother.png,10.0,0.5\n")
    (inputs / "gps_twice.csv").write_text("image,x,y\nimg_1.png,10.0,0.5\nimg_1.png,90.0,0.5\n")
    (inputs / "notes.txt").write_text("a user's notes\n")
    facades = "x0,y0,x1,y1,z_min,z_max,nx,ny,nz,d\n"
    (inputs / "facades.csv").write_text(facades + "0,0,10,0,0,8,0,-1,0,0\n")
    (inputs / "facades_long_normal.csv").write_text(facades + "0,0,10,0,0,8,0,-2,0,0\n")
    (inputs / "facades_nan_normal.csv").write_text(facades + "0,0,10,0,0,8,nan,-1,0,0\n")
    (inputs / "facades_off_plane.csv").write_text(facades + "0,0,10,0,0,8,0,-1,0,3\n")
    (inputs / "facades_empty.csv").write_text(facades)
    (inputs / "empty_dir").mkdir()
    (inputs / "list.yaml").write_text("- 1\n- 2\n")
    (inputs / "broken.yaml").write_text("seed: [1, 2\n")
    (inputs / "unknown.yaml").write_text("blocks_x: 1\nnot_a_key: 3\n")
    (inputs / "empty.yaml").write_text("")
    f = DirichletFilter(alpha=np.linspace(0.5, 3.0, 8))
    f.threshold = 1.0
    f.save(inputs / "dirichlet.json")
    _png(inputs / "a" / "x.png", seed=5)
    _png(inputs / "b" / "x.png", seed=6)
    (root / "outs").mkdir()
    return Env(
        root=root,
        inputs=inputs,
        world=world,
        onnx=onnx_path,
        pt=pt,
        reloc_onnx=reloc_onnx,
        image=inputs / "base" / "img_1.png",
        base=base,
        cache=root / "train_cache",
    )


def user_folder(env: Env, name: str) -> Path:
    """A folder that holds a user's files (and looks like a render output by name)."""
    folder = env.out(name)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "rgb" / "000007.png").write_bytes(b"the user's photo")
    (folder / "poses.csv").write_text("the user's poses\n")
    return folder


def user_file(env: Env, name: str, text: str = "a user's file\n") -> Path:
    path = env.out(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


# ============================================================================ argv builders

Argv = Callable[[Env], list[str]]


@dataclass
class Case:
    command: str
    id: str
    argv: Argv
    match: str = ""  # words the error must contain ("" for argparse usage errors: any)
    expect: str = "error"  # "error", or "ok" for a legal extreme that must succeed


def _world_argv(command: str, extra: tuple[str, ...]) -> Argv:
    """``geoseg render|demo`` on the tiny world, one 32x24 frame, plus ``extra``."""
    return lambda e: [
        *(command, "--config", str(e.world), "--out", str(e.out(command))),
        *("--frames", "1", "--size", "32x24"),
        *[x.format(e=e) for x in extra],
    ]


def render_argv(*extra: str) -> Argv:
    return _world_argv("render", extra)


def demo_argv(*extra: str) -> Argv:
    return _world_argv("demo", extra)


TINY_TRAIN = [
    "--device",
    "cpu",
    "--set",
    "epochs=1",
    "--set",
    "batch_size=1",
    "--set",
    "data.size=[16, 24]",
    "--set",
    "data.synth.seeds=[1]",
    "--set",
    "data.synth.frames=1",
    "--set",
    "data.synth.val.frames=1",
    "--set",
    "class_weight_samples=1",
    "--set",
    "export=false",
    "--set",
    "plots=false",
    "--set",
    "progress=false",
]


def train_argv(*extra: str, trainer: str = "seg", out: str = "train") -> Argv:
    tiny = TINY_TRAIN if trainer == "seg" else ["--device", "cpu", "--set", "progress=false"]
    cache = ["--set", "data.cache_dir={e.cache}"] if trainer == "seg" else []
    return lambda e: [
        "train",
        trainer,
        "--out",
        str(e.out(out)),
        *tiny,
        *[x.format(e=e) for x in (*cache, *extra)],
    ]


def export_argv(*extra: str) -> Argv:
    return lambda e: [
        "export",
        *[x.format(e=e) for x in extra],
    ]


def infer_argv(
    *extra: str, images: tuple[str, ...] = ("{e.image}",), model: str = "{e.onnx}"
) -> Argv:
    return lambda e: [
        "infer",
        *[x.format(e=e) for x in images],
        "--model",
        model.format(e=e),
        "--out",
        str(e.out("infer")),
        *[x.format(e=e) for x in extra],
    ]


def localize_argv(*extra: str, query: str = "{e.image}") -> Argv:
    return lambda e: [
        "localize",
        query.format(e=e),
        "--base",
        str(e.base),
        *PLACEHOLDER_LOCALIZE,
        *[x.format(e=e) for x in extra],
    ]


# the networks-free placeholders (the shipped networks are localize's default)
PLACEHOLDER_LOCALIZE = ("--embedding", "thumbnail", "--relative-pose", "essential")


def infer_output(env: Env) -> Path:
    """A folder written by `geoseg infer` (another command's output)."""
    out = env.out("infer_made")
    if not out.is_dir():
        assert main(["infer", str(env.image), "--model", str(env.onnx), "--out", str(out)]) == 0
    return out


def rendered(env: Env) -> Path:
    """A rendered sequence (a folder of images with its camera.json), rendered once."""
    out = env.root / "rendered"
    if not (out / "meta.json").is_file():
        argv = ["render", "--config", str(env.world), "--out", str(out), "--frames", "3"]
        assert main([*argv, "--size", "64x48"]) == 0
    return out


def slam_buildings(env: Env, facades: str = "facades.csv") -> list[str]:
    """``slam run`` on the rendered sequence with the facade table ``inputs/<facades>``."""
    folder = rendered(env)
    return ["slam", "run", str(folder), "--out", str(env.out("slam")), "--buildings",
            str(env.inputs / facades)]  # fmt: skip


def earlier_run(env: Env) -> Path:
    """A run folder whose last.pt is gone but whose results remain."""
    run = env.out("earlier_run")
    run.mkdir(parents=True, exist_ok=True)
    (run / ".geoseg-output.json").write_text(
        json.dumps({"format": "geoseg-output", "version": 1, "producer": "train", "files": []})
    )
    (run / "best.pt").write_bytes(b"the earlier run's best weights")
    (run / "metrics.csv").write_text("epoch,val_miou\n1,0.8\n")
    return run


# ============================================================================ the runner


def geoseg_wrote(path: Path, stop: Path) -> bool:
    """True when an output marker of a folder above ``path`` records it (a command may rewrite
    its own outputs; everything else must stay as it was)."""
    from geoseg.output_dir import MARKER, recorded_outputs

    if path.name == MARKER:
        return True
    for folder in path.parents:
        if (folder / MARKER).is_file():
            return path.relative_to(folder).as_posix() in recorded_outputs(folder)
        if folder == stop:
            break
    return False


def snapshot(*folders: Path) -> dict[Path, str]:
    """SHA-256 of every file under ``folders`` that geoseg did not record writing."""
    out = {}
    for folder in folders:
        for path in folder.rglob("*"):
            if path.is_file() and not geoseg_wrote(path, folder):
                out[path] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def stub_work(monkeypatch) -> None:
    import geoseg.export
    import geoseg.synth.export
    import geoseg_cli.commands.demo as demo
    import training.loop

    monkeypatch.setattr(geoseg.synth.export, "default_renderer", _accept)
    monkeypatch.setattr(demo, "STEPS", [("accepted", _accept)])
    monkeypatch.setattr(training.loop, "train_one_epoch", _accept)
    monkeypatch.setattr(geoseg.export, "export_onnx", _accept)
    monkeypatch.setattr(runpy, "run_path", _accept)


def classify(argv: list[str], env: Env, capsys, match: str) -> tuple[str, str]:
    """Run ``geoseg argv``: ``(outcome, stderr)``, outcome ``A``/``B``/``C``/``D`` for a bad
    input, ``ok`` when the command succeeded (or reached its real work)."""
    before = snapshot(env.inputs, env.root / "outs")
    try:
        code = main(argv)
    except Accepted:
        code = 0
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code if isinstance(exc.code, int) else 2
    except Exception as exc:  # a traceback for the user
        return "B", f"{type(exc).__name__}: {exc}"
    err = capsys.readouterr().err
    after = snapshot(env.inputs, env.root / "outs")
    changed = [p for p, digest in before.items() if after.get(p) != digest]
    if changed:
        return "D", f"changed or deleted: {changed[:3]}"
    if code == 0:
        return "ok", err
    if code == 2 and "error" in err and match in err:
        return "A", err
    return "C", f"exit {code}, stderr {err[-500:]!r} (expected the words {match!r})"

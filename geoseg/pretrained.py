"""The trained weights shipped inside the package, ``geoseg/weights/<name>/``.

Each folder is a copy of a ``geoseg train`` run directory reduced to what inference and the
benchmarks read (:data:`SHIPPED_FILES`): ``model.pt``, ``model.onnx``, ``model_card.json`` /
``.md`` (data, config, command, metrics, wall time), ``metrics.json`` / ``.csv`` and
``config.yaml``; the Dirichlet folders hold ``dirichlet.json`` and ``max_probability.json``
instead of a network. ``python -m training.ship RUN NAME`` copies a run there; the model card's
``command`` reproduces it (``python -m training.average`` for averaged weights).

Names (:data:`PRETRAINED`): ``seg`` (ENet, 8 classes) and ``seg_real`` (the same for real street
photographs: fine-tuned on the randomised city and weight-averaged, docs/real_images.md);
``normals`` and ``normals_real`` (the joint labels + normals networks on those trunks);
``naive`` (the 2015 patch CNN), ``dirichlet`` (its false-positive filter), ``naive_real`` and
``dirichlet_real`` (the same for real photographs), ``dirichlet_real_synth`` (``naive_real``'s
filter for rendered frames); ``reloc`` and ``relpose`` (the relocalisation heads, when shipped)
and ``relpose_near`` (the relative-pose head for views of one place,
:class:`geoseg.reloc.networks.GatedRelPoseHead`). Each card names its config.

``street`` (the joint network for real street photographs, trained on CamVid's labels:
``configs/street_seg.yaml`` then ``configs/street.yaml``) is *not* inside the package: CamVid's
terms allow research use and reproduction by benchmarks but not weights shipped in the package.
``python -m training.ship runs/street street --user`` installs a run of it into the user weights
folder (:data:`USER_WEIGHTS_DIR`), where every function here finds it by name.
:func:`real_photo_network` names the network for real photographs that commands use by default:
``street`` when installed, else ``normals_real``.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

from geoseg.errors import GeosegError

logger = logging.getLogger(__name__)

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
USER_WEIGHTS_DIR = Path(
    os.environ.get("GEOSEG_WEIGHTS_DIR") or Path.home() / ".local" / "share" / "geoseg" / "weights"
)
"""Weights installed by the user (``python -m training.ship RUN NAME --user``), for networks whose
training data's terms keep them out of the package; ``$GEOSEG_WEIGHTS_DIR`` moves it."""
USER_ONLY: frozenset[str] = frozenset({"street"})
"""Names never shipped inside the package (their training data's terms), only user-installed."""
REAL_PHOTO_NETWORKS: tuple[str, ...] = ("street", "normals_real")
"""Joint networks for real photographs, best first (:func:`real_photo_network`)."""
PRETRAINED: dict[str, str] = {
    "seg": "ENet labels (8 classes)",
    "seg_real": "ENet labels (8 classes) for real street photographs, trained on the randomised city",
    "street": "joint labels + surface normals network for real street photographs, trained on "
    "real labelled frames (CamVid) and the randomised city's normals; user-installed",
    "normals": "joint labels + surface normals network (ENet trunk + normals head)",
    "normals_real": "joint labels + surface normals network for real street photographs "
    "(the seg_real trunk + a normals head trained on the randomised city)",
    "naive": "naive patch CNN (thesis fig. 4.5)",
    "naive_real": "naive patch CNN for real street photographs, trained on the randomised city",
    "dirichlet": "Dirichlet false-positive filter of the naive CNN",
    "dirichlet_real": "Dirichlet false-positive filter of naive_real",
    "dirichlet_real_synth": "Dirichlet false-positive filter of naive_real for synthetic renders",
    "reloc": "relocalisation embedding on the layer-21 features",
    "relpose": "relative-pose head on the layer-21 features",
    "relpose_near": "relative-pose head for views of one place, gated with relpose",
}
SHIPPED_FILES: tuple[str, ...] = (
    "model.pt",
    "model.onnx",
    "model_card.json",
    "model_card.md",
    "metrics.json",
    "metrics.csv",
    "config.yaml",
    "dirichlet.json",
    "max_probability.json",
)


def pretrained_dir(name: str) -> Path:
    """The folder of shipped weights ``name``.

    Raises:
        GeosegError: unknown name, or nothing shipped under it (the message says how to train it).
    """
    if name not in PRETRAINED:
        raise GeosegError(f"pretrained: unknown name {name!r}; known {sorted(PRETRAINED)}")
    for root in (WEIGHTS_DIR, USER_WEIGHTS_DIR):
        if (root / name / "model_card.json").is_file():
            return root / name
    folder = WEIGHTS_DIR / name
    if name == "street":
        raise GeosegError(
            f"pretrained 'street' ({PRETRAINED[name]}): not installed in {USER_WEIGHTS_DIR / name} "
            "(CamVid's terms keep it out of the package); train it with `python -m "
            "training.camvid_holdout CAMVID runs/camvid_holdout`, `geoseg train seg --config "
            "configs/street_seg.yaml`, `geoseg train normals --config configs/street.yaml`, "
            "then `python -m training.ship runs/street street --user`"
        )
    trainer = name.split("_")[0]  # the trainer's name, e.g. relpose for relpose_near
    raise GeosegError(
        f"pretrained {name!r} ({PRETRAINED[name]}): not shipped in {folder}; train it with "
        f"`geoseg train {trainer} --config configs/{name}.yaml`, then "
        f"`python -m training.ship runs/{name} {name}`"
    )


def is_installed(name: str) -> bool:
    """Whether weights ``name`` are in the package or the user weights folder."""
    try:
        pretrained_dir(name)
    except GeosegError:
        return False
    return True


def real_photo_network() -> str:
    """The name of the best installed joint network for real photographs (the default of
    ``geoseg infer`` and of ``geoseg slam run --buildings``): ``street`` when installed, else
    ``normals_real`` (always shipped), with a log line saying how to install ``street``."""
    for name in REAL_PHOTO_NETWORKS:
        if is_installed(name):
            return name
        logger.info("real photographs: %s is not installed, trying the next network", name)
    return REAL_PHOTO_NETWORKS[-1]  # pretrained_dir names what is missing


def pretrained_file(name: str, file: str = "model.pt") -> Path:
    """A file of the shipped weights ``name`` (e.g. ``model.onnx``).

    Raises:
        GeosegError: not shipped, or that file missing.
    """
    path = pretrained_dir(name) / file
    if not path.is_file():
        raise GeosegError(f"pretrained {name!r}: no {file} in {path.parent}")
    return path


def path_or_shipped(path: str | Path, file: str | None = None) -> Path:
    """``path`` itself, or, when no such path exists and it is the name of shipped weights
    (``"seg_real"``), their folder (:func:`pretrained_dir`), or their ``file`` when given
    (:func:`pretrained_file`)."""
    if not Path(path).exists() and str(path) in PRETRAINED:
        return pretrained_dir(str(path)) if file is None else pretrained_file(str(path), file)
    return Path(path)


def model_card(name: str) -> dict[str, Any]:
    """The shipped model card of ``name`` (data, config, command, metrics)."""
    return json.loads(pretrained_file(name, "model_card.json").read_text())


def pretrained_segmenter(name: str = "normals", *, backend: str = "onnx", device: str = "cpu"):
    """A :class:`geoseg.infer.Segmenter` over shipped weights.

    Args:
        name: ``normals`` (labels + normals, the default), ``normals_real``, ``street``
            (when installed; :func:`real_photo_network`), ``seg``,
            ``seg_real``, ``naive`` or ``naive_real``.
        backend: ``onnx`` (onnxruntime) or ``torch``.
        device: ``cpu`` or ``cuda``.

    Raises:
        GeosegError: unknown backend or name, weights not shipped.
    """
    from geoseg.export import available_providers
    from geoseg.infer import Segmenter

    if backend == "onnx":
        return Segmenter.from_onnx(
            pretrained_file(name, "model.onnx"), providers=available_providers(device)
        )
    if backend == "torch":
        return Segmenter.from_checkpoint(pretrained_file(name, "model.pt"), device=device)
    raise GeosegError(f"backend: expected 'onnx' or 'torch', got {backend!r}")

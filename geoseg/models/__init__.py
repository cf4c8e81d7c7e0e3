"""geoseg networks: ENet, the joint labels + normals network, the naive CNN, and the registry.

Use :func:`get_model` (``get_model("joint", num_classes=8)``) or the keyword-only builders
from their modules (``from geoseg.models.enet import enet``). The builders are not re-exported
here: they share their modules' names, and re-exporting them would shadow the submodules.
The relocalisation and relative-pose heads are reached through the registry (``"reloc"``,
``"relpose"``).
"""

from geoseg.models.enet import ENet, count_parameters
from geoseg.models.joint import JointNet
from geoseg.models.naive_cnn import NaiveCNN, NaiveDense
from geoseg.models.registry import get_builder, get_model, list_models

__all__ = [
    "ENet",
    "JointNet",
    "NaiveCNN",
    "NaiveDense",
    "count_parameters",
    "get_builder",
    "get_model",
    "list_models",
]

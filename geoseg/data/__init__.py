"""Torch datasets and augmentations: synthetic frames, Cityscapes-format folders, transforms."""

from geoseg.data.cityscapes import (
    CITYSCAPES_TO_GEOSEG,
    CityscapesDataset,
    map_cityscapes_labels,
)
from geoseg.data.synthetic import (
    EVAL_SEEDS,
    HELDOUT_CONDITIONS,
    PatchDataset,
    SyntheticConfig,
    SyntheticDataset,
    prerender,
    synthetic_config,
)
from geoseg.data.transforms import AugmentConfig, Normals, SampleTransform, build_transforms

__all__ = [
    "EVAL_SEEDS",
    "HELDOUT_CONDITIONS",
    "PatchDataset",
    "SyntheticConfig",
    "SyntheticDataset",
    "prerender",
    "synthetic_config",
    "CITYSCAPES_TO_GEOSEG",
    "AugmentConfig",
    "CityscapesDataset",
    "Normals",
    "SampleTransform",
    "build_transforms",
    "map_cityscapes_labels",
]

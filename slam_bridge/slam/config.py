"""Settings of the SLAM loop: one typed config per stage, collected in :class:`SlamConfig`.

YAML presets (``configs/slam_*.yaml``) override these defaults by key, e.g.
``slam.window.n=20`` or ``slam.tracking.min_tracked=15``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from slam_bridge.errors import SlamError
from slam_bridge.slam.fusion import FusionConfig
from slam_bridge.slam.mapping import MappingConfig
from slam_bridge.slam.tracking import TrackingConfig
from slam_bridge.slam.windows import WindowConfig

__all__ = ["SlamConfig"]


@dataclass
class SlamConfig:
    """The keyframe loop's settings (:func:`slam_bridge.slam.loop.run_slam`).

    Attributes:
        tracking: pose of each new keyframe (:mod:`slam_bridge.slam.tracking`).
        mapping: triangulation, gating, culling (:mod:`slam_bridge.slam.mapping`).
        window: the k-BA window, plain or hybrid (:mod:`slam_bridge.slam.windows`).
        fusion: the barrier fusion (:mod:`slam_bridge.slam.fusion`).
        blas_threads: BLAS/LAPACK threads while the loop runs (threadpoolctl; None leaves the
            library's default). The window's dense systems are small (a 240 x 240 reduced
            camera system), where a second thread costs more than it gives.
    """

    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    blas_threads: int | None = 1

    def __post_init__(self) -> None:
        if self.blas_threads is not None and self.blas_threads < 1:
            raise SlamError(f"blas_threads: expected >= 1 or None, got {self.blas_threads}")

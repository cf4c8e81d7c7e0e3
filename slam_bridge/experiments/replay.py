"""A run's building constraints replayed without its worker: what the fusion costs apart from
the worker beside it.

The asynchronous bridge costs the SLAM's loop two things: the building rows its associations
add to every fused window, and the worker itself (the hook's own time, and the inference and
association competing for the cores). A run against ``nobuild`` measures both together. To
tell them apart, :class:`RecordingConstraints` records, call by call, the association each of
the fusion's calls used in an asynchronous run; :class:`ReplayBridge` then gives the same
associations to the same calls of a second run of the same drive, with no worker: the same
building rows (the same trajectory, since the SLAM is otherwise deterministic), no inference,
no association, no hook.
"""

from __future__ import annotations

from slam_bridge.bridge.association import Association
from slam_bridge.bridge.constraints import BuildingConstraints
from slam_bridge.errors import SlamError

__all__ = ["RecordingConstraints", "ReplayBridge"]

#: ``(keyframe, association used)`` of each of the fusion's calls, in order
Calls = list[tuple[int, Association | None]]


def _same_settings(c: BuildingConstraints) -> dict:
    return dict(sigma_m=c.sigma_m, weight=c.weight, window_weight=c.window_weight)


class RecordingConstraints(BuildingConstraints):
    """``constraints``, recording the association each fusion call used (:attr:`calls`)."""

    def __init__(self, constraints: BuildingConstraints) -> None:
        super().__init__(constraints.facades, **_same_settings(constraints))
        self.association = constraints.association
        self.calls: Calls = []

    def factors(self, slam_map, problem, k: int):
        self.calls.append((k, self.association))
        return super().factors(slam_map, problem, k)


class _ReplayedConstraints(BuildingConstraints):
    def __init__(self, recorded: RecordingConstraints) -> None:
        super().__init__(recorded.facades, **_same_settings(recorded))
        self._calls = iter(recorded.calls)

    def factors(self, slam_map, problem, k: int):
        k_recorded, association = next(self._calls, (None, None))
        if k_recorded != k:
            raise SlamError(
                f"replay: the fusion's call at keyframe {k} was at keyframe {k_recorded} in "
                "the recorded run (the runs diverged)"
            )
        self.association = association
        return super().factors(slam_map, problem, k)


class ReplayBridge:
    """The loop's bridge hook without a worker: the recorded run's associations, call by call.

    Args:
        recorded: the constraints of the recorded run, after it.
    """

    image_at = None

    def __init__(self, recorded: RecordingConstraints) -> None:
        self.constraints = _ReplayedConstraints(recorded)

    def __call__(self, slam_map, k: int, obs) -> None:
        """Nothing: the associations come with the fusion's calls."""

    def finish(self, slam_map) -> None:
        """Nothing to wait for."""

    def close(self) -> None:
        """Nothing to stop."""

"""The pose-graph links of the hybrid windows: frozen references and their weights.

A link ``(z_i, z_{i+1})`` enters the pose graph when ``z_i`` leaves the BA window (thesis §3.5,
eq. 3.4). Two choices make the hybrid k-BA as good as the plain one (not in the thesis, which
takes ``S_hat`` "after the minimisation of zeta" and ``D = I``):

* **Frozen references.** The link keeps the relative pose it had when it entered (eq. 3.2, the
  last estimate before that keyframe's k-BA and fusion) for as long as it stays in the pose
  graph. Re-taken from the already fused poses at every keyframe, each fusion's bend of the chain
  would become the next keyframe's reference and the bends would accumulate. This applies to
  DPC's ``S_hat`` (eq. 3.14), MPC's baseline lengths and MPC's epipolar offsets (their rest
  position is the chain rebuilt from its first camera with the frozen relative poses).
* **Information weights** (DPC, the thesis's perspective §5.2): each link is weighed by the
  information the BA window had on its relative pose when it entered (its points and rows, at
  the window's optimum), times ``info_scale``; links without it (MPC's fallback links, a
  window that could not be factorised) get the constant ``D``.

:class:`LinkMemory` keeps both per link, keyed by keyframe ids.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from slam_bridge.errors import SlamError
from slam_bridge.factors.baseline_length import BaselineLengthFactor
from slam_bridge.factors.pose_graph_dpc import DPCFactor, relative_pose_information
from slam_bridge.factors.pose_graph_mpc import MPCFactor

logger = logging.getLogger(__name__)

__all__ = ["LinkMemory", "camera_covariance"]


class LinkMemory:
    """Frozen relative poses and information weights of pose-graph links (module docstring).

    Args:
        D: ``(6,)`` constant DPC weight ``diag(A, B)`` of links without an entry information.
        info_scale: factor on the information weights (a link stands for the points its two
            cameras share, but the marginal relative-pose covariance counts a camera's noise in
            both of its links, so the raw information leaves the chain soft).
        min_sigma: ``(rad, m)`` floors of the information weights' standard deviations.
    """

    def __init__(self, D: np.ndarray, info_scale: float, min_sigma: tuple[float, float]) -> None:
        self.D = np.asarray(D, dtype=np.float64)
        self.info_scale = float(info_scale)
        self.min_sigma = min_sigma
        self.relative: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.information: dict[tuple[int, int], np.ndarray] = {}

    def freeze(self, problem) -> None:
        """Record the relative pose of every pose-graph pair of ``problem`` not yet known, then
        rebuild its pose-graph terms on the frozen references and the links' weights.

        Args:
            problem: a :class:`slam_bridge.slam.hybrid_problem.HybridProblem` at its pre-k-BA state.
        """
        pg = problem.window.pose_graph_pairs
        st = problem.state
        for a, b in pg:
            key = (int(a), int(b))
            if key not in self.relative:
                i, j = problem.camera_index(a), problem.camera_index(b)
                R_i = st.R_wc[i]
                self.relative[key] = (R_i.T @ st.R_wc[j], R_i.T @ (st.t_wc[j] - st.t_wc[i]))
        if not pg.size:
            return
        ids = problem.camera_ids
        D_const = np.diag(self.D) if self.D.ndim == 1 else self.D
        for i, f in enumerate(problem.vision):
            if isinstance(f, DPCFactor):
                kp = [(int(ids[a]), int(ids[b])) for a, b in f.pairs]
                R_h = np.stack([self.relative[q][0] for q in kp])
                t_h = np.stack([self.relative[q][1] for q in kp])
                W = np.stack([self.information.get(q, D_const) for q in kp])
                problem.vision[i] = DPCFactor(f.pairs, R_h, t_h, W, kernel=f.kernel, name=f.name)
            elif isinstance(f, MPCFactor) and f.offset is not None:
                problem.vision[i] = f.relative_to(self.frozen_chain_state(problem))

    def frozen_chain_state(self, problem):
        """``problem.state`` with the pose-graph chain rebuilt from its first camera by the
        frozen relative poses: every link's relative pose is its reference there."""
        st = problem.state
        R, t = st.R_wc.copy(), st.t_wc.copy()
        for a, b in problem.window.pose_graph_pairs:
            i, j = problem.camera_index(a), problem.camera_index(b)
            R_h, t_h = self.relative[(int(a), int(b))]
            R[j], t[j] = R[i] @ R_h, R[i] @ t_h + t[i]
        return dataclasses.replace(st, R_wc=R, t_wc=t)

    def add_length_terms(self, problem, sigma_m: float | None) -> None:
        """Append a :class:`BaselineLengthFactor` over the pose-graph pairs of ``problem`` (MPC),
        the lengths from the frozen references; nothing when ``sigma_m`` is None."""
        if not sigma_m or not problem.window.pose_graph_pairs.size:
            return
        pairs, lengths = [], []
        for a, b in problem.window.pose_graph_pairs:
            pairs.append((problem.camera_index(a), problem.camera_index(b)))
            lengths.append(float(np.linalg.norm(self.relative[(int(a), int(b))][1])))
        sig = np.full(len(pairs), float(sigma_m))
        problem.vision.append(BaselineLengthFactor(np.array(pairs), np.array(lengths), sig))

    def remember_entry_information(self, problem) -> None:
        """Store the weight of the link the pose graph gains at the next keyframe.

        That link is the BA window's first pair ``(z_{n+1}, z_{n+2})``; ``z_{n+1}`` then leaves
        the BA window with its points. The information this window (at its optimum ``X*``,
        undamped normal equations, eq. 1.32) has on the pair's relative pose is what those
        points and rows gave it (:func:`slam_bridge.factors.pose_graph_dpc.
        relative_pose_information`), times ``info_scale``. Nothing is stored with fewer than
        two BA cameras, a fixed camera in the pair, or a system that cannot be factorised (the
        link then gets the constant ``D``).
        """
        ba = problem.window.ba_cameras
        if ba.size < 2:
            return
        st = problem.state
        ia, ib = problem.camera_index(ba[0]), problem.camera_index(ba[1])
        fa, fb = int(st.camera_index_map[ia]), int(st.camera_index_map[ib])
        if fa < 0 or fb < 0:
            return
        cov = camera_covariance(problem)
        if cov is None:
            return
        idx = np.r_[6 * fa : 6 * fa + 6, 6 * fb : 6 * fb + 6]
        cov_pair = cov[np.ix_(idx, idx)][None]
        R, t = st.R_wc[[ia, ib]], st.t_wc[[ia, ib]]
        info = relative_pose_information(
            R[:1], t[:1], R[1:], t[1:], cov_pair, min_sigma=self.min_sigma
        )
        self.information[(int(ba[0]), int(ba[1]))] = self.info_scale * info[0]

    def forget_from(self, first: int) -> None:
        """Drop the references and weights of the links ending at keyframe ``first`` or later:
        a plain k-BA moved those cameras, the hybrid re-takes them when it resumes."""
        for key in [q for q in self.relative if q[1] >= first]:
            del self.relative[key]
            self.information.pop(key, None)


def camera_covariance(problem) -> np.ndarray | None:
    """``S^-1`` of ``problem``'s undamped vision system (eq. 1.32), ``(6 Cf, 6 Cf)``, or None
    when it cannot be factorised (logged)."""
    from slam_bridge.ba.normal_equations import assemble
    from slam_bridge.ba.solvers.schur import SchurFactorization

    neq = assemble(problem.vision, problem.state)
    try:
        try:
            fac = SchurFactorization(neq, 0.0)
        except SlamError:  # a point left with one valid row: a whisker of damping
            fac = SchurFactorization(neq, 1e-6, "marquardt")
        return fac.camera_covariance_full()
    except SlamError as exc:
        logger.warning("camera covariance: system not factorisable (%s)", exc)
        return None

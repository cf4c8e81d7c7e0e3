"""The incremental keyframe loop of the chapter-3 experiment (thesis §3.7) and its stage.

**Loop** (:func:`run_pipeline`), one keyframe ``k`` at a time, all data of keyframes ``> k``
unseen:

0. *Start-up*: the first ``anchor_keyframes`` (3) keyframes take their ground-truth poses and
   stay fixed. They stand for the start-up the thesis takes for granted (§3.7 evaluates the
   fusion, "a brick of a more general localisation system", on a SLAM already expressed in the
   GPS's projected frame): they fix the metric scale and the georeferenced frame once; from
   then on only the GPS fusion keeps the reconstruction georeferenced (the monocular SLAM
   drifts in 7 DoF otherwise). The points both anchors see are triangulated.
1. *Tracking*: pose of ``k`` by PnP (RANSAC + LM, :func:`slam_bridge.geometry.pnp`) on its
   observations of already triangulated points, or the constant-velocity prediction refined on
   its inliers when it explains more of them (:func:`_track`); too few inliers is an error; PnP outliers are deactivated.
2. *Mapping*: points seen by ``k`` and not yet triangulated are triangulated from all their
   active observations (DLT + refinement, parallax >= ``min_parallax_deg``); a point whose worst
   observation errs by more than ``outlier_gate_px`` loses that observation and waits.
3. *k-BA* (the SLAM's own, unconstrained), ``X* = argmin zeta``. ``n = 0``: the plain window
   of the ``l`` latest keyframes, all their observations, older observers fixed
   (:mod:`slam_bridge.window`), by Levenberg-Marquardt. Hybrids (DPC, MPC, default
   ``kba_window="hybrid"``): the hybrid window of eq. 3.4 with
   ``n_eff = max(0, min(n, l_eff - (l - n)))`` pose-graph cameras (the BA window keeps
   ``l - n`` cameras while fewer than ``l`` keyframes exist) is the k-BA, so the fusion and
   the next k-BA minimise the same ``zeta`` and a fusion is not undone by the next keyframe.
   Three documented departures keep that SLAM as good as the plain one (``PipelineConfig``):
   the pose-graph cameras keep their observations of the BA window's points
   (``pose_graph_rows``, thinned to ``pose_graph_share``), each link keeps the reference it
   had when it entered the pose graph (``freeze_links``), and DPC links are weighed by the
   information the BA window had on them then (``dpc_weight``). Points only the pose-graph
   cameras see leave the problem (eq. 3.4) and are carried along with their newest observer
   (:func:`_carry_points`). ``kba_window="plain"`` runs the plain k-BA for every method and
   uses eq. 3.4 only as the fusion's ``zeta`` (the next k-BA then undoes most of each hybrid
   fusion: measured in ``PipelineConfig.kba_window``).
   *Consistency check* (hybrids, ``consistency_share``): a hybrid window whose ``X*`` leaves
   more than 1 % of its BA-window rows over 4 px cannot fit its own observations; that
   keyframe runs the plain ``n = 0`` k-BA and fusion instead (logged, ``KeyframeRecord.
   fallback``, counted in the time and memory figures).
4. *Fusion*: barrier GPS fusion of the most recent camera (eq. 3.1, :func:`slam_bridge.solvers.
   barrier.solve_barrier`) from ``X*`` over the fusion's ``zeta`` (plain reprojection for
   ``n = 0``, eq. 3.4 for the hybrids; its Hessian is the one the memory and time per iteration
   measure). A keyframe without a GPS fix (dropout, NaN) is not fused (documented behaviour;
   it keeps ``X*``).
5. *Gating*: active observations of the fusion window erring by more than ``window_gate_px``
   after the fusion are deactivated (gross outliers that slipped through). The hybrids' pose-graph
   observations are not gated there (the fusion moved their cameras but not the points only
   they see; the next k-BA reconciles them); every observation was gated while its camera was
   in the BA window. Then the window's points whose views' rays now meet at less than
   ``min_parallax_deg``, or that lie behind a view, are untriangulated (to be triangulated anew
   when seen again). In a sharp turn the optimisation had slid points seen from close
   viewpoints kilometres along their rays (76 of the 117 points keyframe 247 of the 640 m drive
   tracked, DPC, sigma_b = 0), the reprojection gate could not see it, and PnP found no inliers.

Recorded per keyframe (:class:`KeyframeRecord`): the online pose, BA and fusion times, fusion
iterations and time per iteration, the **Hessian memory** and window sizes.

**Hessian memory** (fig. 3.7), the same definition for every method: the bytes of the blocks the
assembled (symmetric) system of ``zeta`` stores, in float64::

    bytes = 8 (36 Cf + 36 Q + 18 N_W + 9 Pf)

with ``Cf`` free cameras (``U`` diagonal blocks, 6x6), ``Q`` pairs of free cameras coupled by a
pose-graph term (off-diagonal camera blocks, 6x6, stored once), ``N_W`` distinct (free camera,
free point) pairs with an observation (``W`` blocks, 6x3) and ``Pf`` free points (``V`` blocks,
3x3). The GPS term only adds to one ``U`` block and the barrier's rank-1 term is never formed
(Sherman-Morrison), so neither changes the count.

**Stage** (:func:`run_experiment`, DESIGN §3.1): config in, directory out, skipped when the
directory already holds the results of the same config.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from geoseg.errors import check_finite, check_positive, check_shape
from slam_bridge.camera import project
from slam_bridge.errors import SlamError
from slam_bridge.factors.gps import GPSFactor
from slam_bridge.factors.pose_graph_dpc import DPCFactor
from slam_bridge.factors.reprojection import ReprojectionFactor
from slam_bridge.geometry import pnp, ray_parallax_deg, triangulate
from slam_bridge.landmarks import LandmarkConfig, Observations
from slam_bridge.solvers.barrier import BarrierConfig, solve_barrier
from slam_bridge.solvers.lm import LMConfig
from slam_bridge.solvers.robust import get_kernel
from slam_bridge.window import (
    HybridWindowConfig,
    WindowError,
    build_hybrid_problem,
    minimize_zeta,
)

logger = logging.getLogger(__name__)

__all__ = [
    "METHODS",
    "PipelineConfig",
    "SequenceData",
    "KeyframeRecord",
    "PipelineResult",
    "SequenceConfig",
    "ExperimentConfig",
    "BaselineLengthFactor",
    "hessian_bytes",
    "run_pipeline",
    "make_sequence",
    "gps_for_setting",
    "run_experiment",
]

#: method name -> (pose-graph kind, uses the pose-graph window)
METHODS = {"ba": ("dpc", False), "dpc": ("dpc", True), "mpc": ("mpc", True)}


@dataclass
class PipelineConfig:
    """Settings of the keyframe loop (module docstring; thesis §3.7: ``l = 40``, ``n = 30``).

    Attributes:
        l: optimised keyframes.
        n: pose-graph cameras for the hybrid methods (``ba`` always uses 0).
        ba_iterations: Levenberg-Marquardt iterations of the k-BA (``X*``).
        fusion_iterations: barrier iterations.
        fusion_backtracks: halvings of a barrier step that crosses the barrier before its
            damping is raised (:attr:`slam_bridge.solvers.barrier.BarrierConfig.max_backtracks`;
            0 = the thesis's Levenberg-Marquardt alone). Measured, 3 against 0: total fusion
            time over 28-32 windows of the bench drive -18 % (``n = 0``), -37 % (DPC), -29 %
            (MPC); over seven drives of the chapter-3 grid MPC's inlier loss with a biased GPS
            +1.3 %, DPC's at sigma_b = 1.5 m -1.1 % (:mod:`slam_bridge.solvers.barrier`).
        gamma_rel: relative barrier weight (:class:`BarrierConfig`).
        t_ratio: ``t = t_ratio zeta(X*)``.
        gps_weight: weight of the GPS term.
        fuse: run the GPS fusion (False: vision only).
        anchor_keyframes: first keyframes set to ground truth and held fixed.
        pnp_threshold_px: PnP RANSAC threshold.
        outlier_gate_px: an observation erring more than this at its PnP pose, or a new
            point's worst observation erring more after triangulation, is a gross outlier
            (deactivated). Moderate errors (a point triangulated with little parallax) are
            left to the k-BA.
        window_gate_px: observations erring more after the fusion are deactivated.
        min_parallax_deg: triangulation parallax threshold.
        min_tracked: fewer PnP inliers make a weak tracking (warning; no outlier gating at
            that pose); fewer than 6 is a lost tracking (:class:`SlamError`).
        history_keyframes: keyframes older than the window handed to the window builder (the
            fixed older observers of its points are found among them).
        dpc_sigma_rot_rad: DPC weight ``A = I / sigma_rot^2`` (eq. 3.16). The thesis's
            ``D = I`` weighs a relative-pose error of 1 m like one squared pixel, which lets
            the barrier bend the pose graph by metres for free (measured: 4-5 m errors). A
            link replaces the reprojection rows of every point its two cameras share; with
            0.1 mrad / 1 mm (160 m run, sigma_b = 0.75 and 1.5 m) the hybrid keeps the n = 0
            inlier count, while 0.2 mrad / 2 mm let the fusion bend the chain at the BA /
            pose-graph junction (4.5 % inlier loss) and 0.05 mrad / 0.5 mm make the chain so
            stiff that the GPS moves the cameras less (xy error x2) (plain k-BA; with the
            hybrid k-BA see ``dpc_weight``).
        dpc_sigma_trans_m: DPC weight ``B = I / sigma_trans^2``.
        dpc_weight: ``"information"`` (default): each pose-graph link ``(z_i, z_{i+1})`` is
            weighed by the information of its relative pose (the thesis's perspective §5.2),
            times ``dpc_info_scale``: with ``kba_window="hybrid"`` the information the BA window
            had on it when ``z_i`` left the window (:func:`_entry_information`, kept with the
            link), with ``"plain"`` the one of this keyframe's k-BA (:func:`_link_information`).
            ``"constant"``: ``D = diag(I / sigma_rot^2, I / sigma_trans^2)`` for every link
            (``dpc_sigma_*``; MPC's DPC fallback links always use it). A constant ``D`` is
            fragile: measured on the 640 m run (hybrid k-BA, frozen links, sigma_b = 0), 0.05
            mrad / 0.5 mm gives 0.14 m mean translation error, 0.04 mrad / 0.4 mm 0.27 m and
            0.025 mrad / 0.25 mm 1.03 m (too stiff: the barrier's slack no longer moves the
            newest camera onto the fix), while softer constants lose inliers under GPS noise.
        dpc_info_scale: factor on the information weights. A link stands for the points its
            two cameras share, but the marginal relative-pose covariance counts a camera's
            noise in both of its links, so x1 leaves the chain soft: measured (640 m, hybrid
            k-BA, sigma_b = 0) x1: 0.48 m (z 0.48 m), x10: 0.24 m. With the plain k-BA the
            calibrated scale (``dpc_info_calibrate``) made it too stiff (tracking lost at
            keyframe 300) and x10 ran through.
        dpc_info_calibrate: ``kba_window="plain"`` only: rescale the information weights of the chain so that the
            covariance of the chain's newest camera ``z_{n+1}`` about the fixed ``z_0`` (the
            translation block's trace) equals its covariance in the k-BA
            (:func:`_chain_scale`). The marginal relative-pose covariances count the noise of a
            camera shared by two links twice (it enters them with opposite signs), so a chain
            of independent links with those weights is softer than the k-BA it stands for.
        fusion_guard_share: hybrids only (``None``: off): reject a fusion (keep ``X*``, log a
            warning) when it raises the share of the fusion window's reprojection rows erring
            by more than ``fusion_guard_px`` (or turning invalid) by more than this share. The
            barrier bounds zeta, not how it spreads: with few points (a sharp turn) the whole
            5 % slack can land on a handful of rows, and the next keyframe then loses its
            tracking. A documented graceful behaviour, not in the thesis. Measured (640 m,
            sigma_b = 0.75 m, constant D, share 0.02): it does not prevent the tracking loss at
            keyframe 247, so it is off by default.
        fusion_guard_px: pixel threshold of that test (the inlier threshold of §3.7).
        dpc_min_sigma: ``(rad, m)`` floors of the information weights' standard deviations.
        mpc_sigma_px: pixel sigma of the MPC epipolar residuals (eq. 3.18). Like DPC's
            ``dpc_info_scale`` (x10), the chain needs more weight than the measurement noise
            gives (with 1 px noise an epipolar distance errs by ~1.4 px): left soft, every later
            fusion bends it and the bend of its oldest link freezes into the fixed history.
            Measured on the 640 m grid with the plain k-BA (sigma_b 0 / 0.75 / 1.5 / bias, mean
            translation error, worst inlier loss vs n = 0): 1.0 px: 1.60 / 1.13 / 1.36 / 0.90
            m, 3.2 %; 0.5 px: 1.20 / 1.15 / 1.02 / 4.04 m, 1.8 %; 0.25 px: 0.76 / 0.71 / 0.77
            / 2.34 m, 0.5 %. With the hybrid k-BA (sigma_b = 0.75 m, 2 mm lengths): 0.5 px
            0.40 m, 7.9 % inlier loss; 0.25 px 0.21 m, 2.3 %; 0.15 px 0.20 m, 2.0 %. With 5 mm
            lengths, per setting (sigma_b 0 / 0.75 / 1.5 / bias): 0.25 px 0.14 / 0.16 / 0.34 /
            1.24 m, 0.5 / 1.2 / 1.35 / 3.3 %; 0.15 px 0.18 / 0.20 / 0.41 / 1.11 m, 1.1 / 1.1 /
            0.5 / 1.4 %. Differences of this size change from run to run of one sequence with
            any small change (the height drift is chaotic), so neither is clearly better.
        mpc_length_sigma_m: MPC only: sigma of a baseline-length term
            ``((||T_j - T_i|| - L_hat_ij) / sigma)^2`` added to zeta for every pose-graph pair
            (:class:`BaselineLengthFactor`, ``L_hat`` from the pre-fusion poses). The epipolar
            residual of eq. 3.18 is blind to the length of each baseline, so without it every
            link of the chain, and the scale of the BA window behind it, is free: the barrier
            lets the GPS slide the reconstruction along those directions at no vision cost (the
            sequence drifts by tens of metres; hybrid k-BA, sigma_b = 1.5 m: 3.9 m mean
            error). ``None`` = the thesis's pure MPC. Measured (640 m, hybrid k-BA, sigma_b =
            1.5 m, inlier loss vs n = 0): 1 mm 3.7 %, 2 mm 3.0 %, 3 mm 2.5 %, 5 mm 1.3 %,
            10 mm 1.8 %; with 5 mm, sigma_b 0 / 0.75 / bias: 0.5 / 1.2 / 3.3 % (2 mm: 0.7 /
            2.3 / 3.0 %).
        pose_graph_share: share ``s`` of the points (a fixed subset, chosen by point id) whose
            observations in the pose-graph keyframes stay in the window: MPC's 2D
            correspondences between successive pose-graph keyframes (eq. 3.18; the thesis does
            not say how many; all of them make MPC slower than n = 0) and the
            ``pose_graph_rows``. Their rows are weighted by ``1 / s`` (:func:`_hybrid_problem`).
            Measured (640 m, DPC, sigma_b = 0.75 m): all pose-graph rows: Hessian memory 2.4x
            smaller than n = 0 (fig. 3.7 wants >= 3x), time per fusion iteration 0.46x; s =
            0.25 with the 1 / s weight: memory 3.2x smaller, no inlier loss; s = 0.25 unweighted:
            3.2 % inlier loss; s = 0.5 unweighted: 2.9x smaller. The hybrid drifts more in
            height than n = 0 (the GPS fixes x, y only): over seven drives (``sequence.seed``
            0, 3, 4, 6-9; sigma_b = 0) mean height error DPC 0.29 m vs n = 0 0.18 m, horizontal
            0.04 vs 0.06 m; per drive the height error is chaotic (seed 3: s = 0.25 0.57 m,
            s = 0.5 0.11 m, s = 1 0.30 m; seed 0: 0.15 / 0.38 m for s = 0.25 / 0.5), and s =
            0.5 is no better on average (0.38 m mean error vs 0.30 m).
        refine_left_points: after the last keyframe, re-triangulate the points that left a
            hybrid window with the final poses (:func:`_refine_points`), so that the returned
            map matches the returned trajectory (which it does not change). Refitting them
            during the run instead (every carried point at every keyframe) doubled the loop's
            time, and refitted points tracked again changed the trajectory.
        pose_graph_rows: the hybrid window keeps the pose-graph cameras' observations of the BA
            window's points (:attr:`slam_bridge.window.HybridWindowConfig.pose_graph_rows`).
            Measured (640 m, sigma_b = 0, hybrid k-BA, DPC, frozen constant links): 0.93 m mean
            translation error without, 0.18 m with.
        ba_scale_sigma_m: hybrids only: sigma of a baseline-length term on the first pair of
            the BA window. With ``n > 0`` no fixed camera observes the BA window's points, so
            its scale (about ``z_{n+1}``) costs zeta nothing and the barrier lets each GPS fix
            rescale it, at the expense of its consistency with the pose-graph cameras' points
            (inlier loss). ``None`` (default) = eq. 3.4 as written.
        freeze_links: keep each pose-graph link's reference (DPC's ``S_hat``, eq. 3.14, MPC's
            baseline lengths and epipolar offsets) from the moment it entered the pose graph
            rather than re-taking it before every fusion (:func:`_pose_graph_references`). With
            the hybrid k-BA a re-taken reference makes every fusion's bend permanent: measured
            (640 m, sigma_b = 0.75 m, DPC, constant 0.1 mrad / 1 mm) 15 % inlier loss vs n = 0
            re-taken, 3.4 % frozen; MPC 10 % vs 3.2 %. With the plain k-BA (which
            re-estimates the pose-graph cameras at every keyframe) a frozen reference fights
            it.
        kba_window: ``"hybrid"`` (default, the thesis's reading: §3.5.0.1 takes ``S_hat``
            "after the minimisation of zeta"): the hybrid window (eq. 3.4) *is* the SLAM's k-BA
            of the hybrid methods, minimised by ``ba_iterations`` LM iterations, and the fusion
            starts from its optimum. ``"plain"``: the SLAM's k-BA at every keyframe is the
            plain ``n = 0`` window of the ``l`` latest keyframes for every method, and the
            hybrid window is only the fusion's ``zeta``, built on the k-BA's output and
            minimised (``zeta_iterations``) to get ``X*``. Then the fusion minimises a ``zeta``
            other than the one the next k-BA minimises, and that k-BA undoes most of it:
            measured (640 m, sigma_b = 0) the newest camera was 0.69 m (DPC) / 0.87 m (MPC)
            from its exact GPS fix before each fusion (n = 0: 0.11 m) and the mean translation
            error 0.66 / 0.76 m, vs 0.16 / 0.14 m with the hybrid k-BA (``pose_graph_rows``,
            ``freeze_links``). Vision only (no GPS, 640 m): hybrid k-BA 1.0 m (DPC) / 1.1 m
            (MPC, 2 mm lengths) mean error, plain n = 0 1.8 m; over seven drives with GPS the
            hybrids drift more in height (``pose_graph_share``). ``"ba"``: the k-BA is the
            plain window of the ``l - n`` BA cameras.
        mpc_relative: MPC's epipolar distances measured from their values after the k-BA
            (:attr:`slam_bridge.window.HybridWindowConfig.mpc_relative`).
        zeta_iterations: ``kba_window="plain"`` only: LM iterations of ``X* = argmin zeta``
            (hybrid ``zeta``, started from the k-BA's output, so a few suffice).
        cull_degenerate_points: after the gating, untriangulate the window's points whose
            observers' rays now meet at less than ``min_parallax_deg`` or that are behind one
            of them (:func:`_cull_degenerate_points`; they are triangulated anew when seen
            again).
        blas_threads: BLAS/LAPACK threads while the loop runs (threadpoolctl; ``None`` leaves
            the library's default). The window's dense systems are small (a 240 x 240 reduced
            camera system), where threads cost more than they give. Measured on the 2-core
            machine with a one-thread training on the other core: a 240 x 240 Cholesky takes
            0.21 ms with one thread, 0.33 ms with two (median; single calls inside the loop up
            to 25 ms); the full 640 m BA/GPS run averaged 171 ms per fusion iteration with
            OpenBLAS's default two threads (7.4 ms on an idle machine), and 130 keyframes of
            BA, DPC and MPC took 14-16 s each with one thread.
        reprojection_kernel: robust kernel of every window's reprojection rows (``None``: least
            squares, the thesis's k-BA; ``"huber"``, ``"geman_mcclure"``), also inside ``zeta``
            during the fusion. Measured (640 m grid, Huber at 2.45 px, drives 0, 3, 7, 8): the
            hybrids' inlier loss rose (sigma_b 0.75: DPC 2.7 %, MPC 3.7 % mean), the time ratios
            rose (DPC 0.39-0.42) and ``n = 0`` lost its tracking on drive 8 (bias), so it is off.
        reprojection_kernel_px: its threshold in pixels
            (:attr:`slam_bridge.window.HybridWindowConfig.reprojection_kernel_scale`).
        consistency_share: hybrids only (``None``: off): when more than this share of the BA
            window's reprojection rows err by more than ``consistency_px`` at ``X*``, the window
            cannot fit its own observations (with 1 px noise a row exceeds 4 px with
            probability ``exp(-8) = 0.03 %``; measured per keyframe on the 640 m run, sigma_b =
            1.5 m: at most 0.6 % for DPC and MPC on drive 0, 0.27 % for ``n = 0`` on drive 7),
            and this keyframe runs the plain ``n = 0`` k-BA (``consistency_iterations``) and
            fusion instead, forgetting the frozen references of the window's links (re-taken
            from the repaired poses when the hybrid resumes). A documented graceful behaviour,
            not in the thesis. Why: on drive 7 (``sequence.seed=7``), sigma_b = 1.5 m, DPC
            tracked keyframes 263-265 of a turn with 19-54 PnP inliers; from there the BA
            window's misfit grew (rows over 4 px at ``X*``: 1 % at keyframe 265, 13 % at 272,
            still 15 000 of cost after 100 LM iterations with the pose-graph terms removed: a
            wrong basin, not a conflict with the links), the estimated keyframe spacing shrank
            from 2 m to 0.2 m and the trajectory ran 79 m from GPS fixes it could no longer
            reach (7.7 m mean error). Any small change of settings avoids that run's failure
            (chaotic), so the check is judged over drives: 640 m grid on drives 0, 3, 4, 6-9,
            means without / with it, sigma_b 0 / 0.75 / 1.5 / bias: DPC translation 0.30 / 0.63
            / 1.65 / 2.34 m -> 0.31 / 0.54 / 0.66 / 1.79 m, inlier loss 0.9 / 1.6 / 2.9 / 2.3 %
            -> 0.9 / 1.4 / 1.5 / 1.9 %; MPC 0.38 / 0.53 / 1.17 / 1.39 m -> 0.26 / 0.52 / 0.76 /
            1.44 m, 1.3 / 2.6 / 3.6 / 2.7 % -> 1.3 / 2.4 / 3.2 / 2.9 %. Runs fell back on 0-6
            keyframes, except drive 7 bias (DPC, 39 keyframes, still 4.5 m mean error: the
            plain k-BA started from the damaged window does not fully repair it; gating its
            rows at 4 px on those keyframes made it worse, 7.2 m).
        consistency_px: the pixel error of that test.
        consistency_iterations: LM iterations of the fallback's plain k-BA.
        weak_track_inliers: hybrids only (``None``: off): while a keyframe tracked with fewer
            PnP inliers than this is in the BA window (its ``l - n`` latest keyframes), the
            window stays plain (``n = 0``: k-BA and fusion), and the links of its pose-graph
            range are re-taken when the hybrid resumes. A hybrid leans on the k-BA of its few
            BA-window cameras; a weakly tracked keyframe (a sharp turn, 15-26 inliers against
            the usual 100-250) needs the whole window to be placed. Not in the thesis (its SLAM
            is assumed to track well). Why: on drive 7, bias run, DPC tracked keyframe 264 with
            15 inliers (50 at 263); the hybrid window placed it and the next two 2-4 m off, the
            consistency check fired only at 267, when the map was already corrupt, and the run
            ended at 4.5 m mean error (39 keyframes fell back); with this rule at 30: 1.1 m.
            Measured over drives 3, 4, 6-9 at 30 (``python bench/fusion_ch3.py --full --drives
            3 4 6 7 8 9 --set pipeline.weak_track_inliers=30``), means off / on, sigma_b 0 /
            0.75 / 1.5 / bias: DPC translation 0.33 / 0.59 / 0.70 / 1.88 -> 0.21 / 0.59 / 1.15 /
            1.39 m (worst bias run 4.45 -> 2.25 m), inlier loss 0.9 / 1.7 / 1.7 / 2.1 -> 0.9 /
            1.2 / 1.1 / 1.0 %; MPC 0.28 / 0.58 / 0.83 / 1.47 -> 0.21 / 0.52 / - / 1.36 m, loss
            1.4 / 2.6 / 3.5 / 2.9 -> 1.0 / 1.6 / - / 2.5 % (MPC lost tracking on drive 9 at
            sigma_b 1.5). But every drive has one to four turns tracked with 8-29 inliers, so
            14-53 keyframes per run fell back: mean time ratios 0.44 / 0.71 -> 0.47 / 0.74, mean
            memory ratio 3.24 -> 2.91 (below the 3x target). A trade, left off by default.
        weak_track_span: with ``weak_track_inliers``, how many keyframes from the weak one on
            stay plain (``None``: while it is in the BA window, ``l - n``; 1: only the weak
            keyframe itself, whose plain k-BA places it with the whole window). Measured at
            30 / 1 (same drives, off -> on): 2.5-4.3 keyframes per run fall back, memory ratio
            3.21, time ratios 0.46 / 0.75; DPC translation 0.33 / 0.59 / 0.70 / 1.88 -> 0.23 /
            0.64 / 0.87 / 1.35 m (drive 7 bias 4.45 -> 2.20 m), loss 0.9 / 1.7 / 1.7 / 2.1 ->
            0.9 / 1.1 / 1.4 / 1.4 %; MPC 0.28 / 0.58 / 0.83 / 1.47 -> 0.23 / 0.65 / - / 1.63 m,
            loss 1.4 / 2.6 / 3.5 / 2.9 -> 1.1 / 2.1 / - / 3.0 % (again lost tracking on drive
            9 at sigma_b 1.5; worst MPC bias run 1.7 -> 2.9 m). Better at sigma_b 0 and in the
            bias runs of DPC, worse elsewhere: not a default either.
        weak_track_n: with ``weak_track_inliers``, the pose-graph cameras of such a window
            (``0``: plain; else a hybrid window with this smaller ``n``, whose larger BA window
            places the weak keyframe at a fraction of the plain window's memory and time).
            Measured at 30 inliers, whole span, n = 15, over the bench drive and drives 3, 4,
            6-9 (means off -> on, sigma_b 0 / 0.75 / 1.5 / bias): DPC translation 0.31 / 0.54 /
            0.66 / 1.79 -> 0.26 / 0.61 / 0.85 / 1.45 m (worst bias run 4.45 -> 2.09 m), inlier
            loss 0.9 / 1.4 / 1.5 / 1.9 -> 1.0 / 1.6 / 1.4 / 1.7 %; MPC 0.26 / 0.52 / 0.76 / 1.44
            -> 0.24 / 0.50 / 0.75 / 1.43 m, loss 1.3 / 2.4 / 3.2 / 2.9 -> 1.0 / 2.6 / 3.4 / 2.8
            %; memory ratio 3.25 -> 3.08. It repairs DPC's bias divergence at a smaller cost than
            the plain window but does not lower the inlier losses: left at 0.
    """

    l: int = 40
    n: int = 30
    ba_iterations: int = 10
    fusion_iterations: int = 10
    fusion_backtracks: int = 3
    gamma_rel: float = 0.01
    t_ratio: float = 1.05
    gps_weight: float = 1.0
    fuse: bool = True
    anchor_keyframes: int = 3
    pnp_threshold_px: float = 8.0
    outlier_gate_px: float = 20.0
    window_gate_px: float = 8.0
    min_parallax_deg: float = 1.0
    min_tracked: int = 12
    history_keyframes: int = 30
    dpc_sigma_rot_rad: float = 1e-4
    dpc_sigma_trans_m: float = 1e-3
    dpc_weight: str = "information"
    dpc_info_scale: float = 10.0
    dpc_min_sigma: tuple[float, float] = (1e-6, 1e-5)
    dpc_info_calibrate: bool = False
    fusion_guard_share: float | None = None
    fusion_guard_px: float = 2.0
    mpc_sigma_px: float = 0.25
    mpc_length_sigma_m: float | None = 5e-3
    pose_graph_share: float = 0.25
    ba_scale_sigma_m: float | None = None
    freeze_links: bool = True
    kba_window: str = "hybrid"
    mpc_relative: bool = True
    zeta_iterations: int = 5
    blas_threads: int | None = 1
    cull_degenerate_points: bool = True
    pose_graph_rows: bool = True
    refine_left_points: bool = True
    reprojection_kernel: str | None = None
    reprojection_kernel_px: float | None = None
    consistency_share: float | None = 0.01
    consistency_px: float = 4.0
    consistency_iterations: int = 50
    weak_track_inliers: int | None = None
    weak_track_span: int | None = None
    weak_track_n: int = 0

    def __post_init__(self) -> None:
        if self.blas_threads is not None and self.blas_threads < 1:
            raise SlamError(f"blas_threads: expected >= 1 or None, got {self.blas_threads}")
        if self.anchor_keyframes < 2:
            raise SlamError(f"anchor_keyframes: expected >= 2, got {self.anchor_keyframes}")
        if self.l < 3:
            raise SlamError(f"l: expected >= 3 (BA window of at least 3 cameras), got {self.l}")
        if not 0 <= self.n <= self.l - 3:
            raise SlamError(f"n: expected 0 <= n <= l - 3 = {self.l - 3}, got {self.n}")
        if self.dpc_weight not in ("information", "constant"):
            raise SlamError(
                f"dpc_weight: expected 'information' or 'constant', got {self.dpc_weight!r}"
            )
        if not 0 < self.pose_graph_share <= 1:
            raise SlamError(f"pose_graph_share: expected in (0, 1], got {self.pose_graph_share}")
        if not self.dpc_info_scale > 0:
            raise SlamError(f"dpc_info_scale: expected > 0, got {self.dpc_info_scale}")
        if self.consistency_share is not None and not 0 <= self.consistency_share < 1:
            raise SlamError(
                f"consistency_share: expected in [0, 1) or None, got {self.consistency_share}"
            )
        check_positive("consistency_px", self.consistency_px)
        if self.consistency_iterations < 1:
            raise SlamError(
                f"consistency_iterations: expected >= 1, got {self.consistency_iterations}"
            )
        if self.reprojection_kernel_px is not None:
            check_positive("reprojection_kernel_px", self.reprojection_kernel_px)
        get_kernel(self.reprojection_kernel)  # an unknown name: SlamError now, not at keyframe 3
        if self.weak_track_inliers is not None and self.weak_track_inliers < 1:
            raise SlamError(
                f"weak_track_inliers: expected >= 1 or None, got {self.weak_track_inliers}"
            )
        if self.weak_track_span is not None and self.weak_track_span < 1:
            raise SlamError(f"weak_track_span: expected >= 1 or None, got {self.weak_track_span}")
        if not (self.weak_track_n == 0 or 0 < self.weak_track_n < self.n):
            raise SlamError(f"weak_track_n: expected 0 or in (0, n), got {self.weak_track_n}")
        if self.kba_window not in ("plain", "ba", "hybrid"):
            raise SlamError(
                f"kba_window: expected 'plain', 'ba' or 'hybrid', got {self.kba_window!r}"
            )


@dataclass
class SequenceData:
    """Everything the loop consumes (ground truth only for the anchors and the evaluation).

    Attributes:
        K: ``(3, 3)`` intrinsics.
        image_size: ``(W, H)``.
        timestamps: ``(C,)`` keyframe times, seconds.
        R_wc_true: ``(C, 3, 3)`` true keyframe rotations.
        t_wc_true: ``(C, 3)`` true optical centres.
        observations: the keyframe observations (sorted by keyframe).
        num_points: number of landmarks ``P`` (point ids ``0..P-1``).
        gps_xy: ``(C, 2)`` GPS fix of each keyframe (NaN = dropout).
    """

    K: np.ndarray
    image_size: tuple[int, int]
    timestamps: np.ndarray
    R_wc_true: np.ndarray
    t_wc_true: np.ndarray
    observations: Observations
    num_points: int
    gps_xy: np.ndarray

    def __post_init__(self) -> None:
        C = self.R_wc_true.shape[0]
        check_shape("R_wc_true", self.R_wc_true, (None, 3, 3))
        check_shape("t_wc_true", self.t_wc_true, (C, 3))
        check_shape("gps_xy", self.gps_xy, (C, 2))
        check_finite("uv", self.observations.uv)
        if np.any(np.diff(self.observations.keyframe) < 0):
            raise SlamError("observations: expected to be sorted by keyframe")

    @property
    def num_keyframes(self) -> int:
        """``C``."""
        return int(self.R_wc_true.shape[0])


@dataclass
class KeyframeRecord:
    """What happened at one keyframe.

    Attributes:
        keyframe: its index.
        n_pose_graph: pose-graph cameras used.
        n_cameras: free cameras of the window.
        n_points: free points of the window.
        n_tracked: PnP inliers.
        n_new_points: points triangulated at this keyframe.
        n_culled: points untriangulated after the fusion (degenerate geometry,
            :func:`_cull_degenerate_points`).
        ba_seconds: wall time of ``X* = argmin zeta``.
        ba_iterations: its LM iterations.
        fusion_seconds: wall time of the barrier fusion (0 if not fused).
        fusion_iterations: barrier iterations.
        fusion_seconds_per_iteration: mean time of a barrier iteration (assembly + solves).
        hessian_bytes: memory of the assembled system (module docstring).
        gps_used: whether a fix was fused.
        zeta_star: ``zeta(X*)``.
        zeta: ``zeta`` after the fusion.
        fallback: the hybrid window failed the consistency check (``consistency_share``) or
            held a weakly tracked keyframe (``weak_track_inliers``): this keyframe ran the
            plain ``n = 0`` k-BA and fusion (or the smaller ``weak_track_n``).
    """

    keyframe: int
    n_pose_graph: int = 0
    n_cameras: int = 0
    n_points: int = 0
    n_tracked: int = 0
    n_new_points: int = 0
    n_culled: int = 0
    ba_seconds: float = 0.0
    ba_iterations: int = 0
    fusion_seconds: float = 0.0
    fusion_iterations: int = 0
    fusion_seconds_per_iteration: float = 0.0
    hessian_bytes: int = 0
    gps_used: bool = False
    zeta_star: float = 0.0
    zeta: float = 0.0
    fallback: bool = False


@dataclass
class PipelineResult:
    """Output of :func:`run_pipeline`.

    Attributes:
        method: ``ba``, ``dpc`` or ``mpc``.
        R_wc: ``(C, 3, 3)`` final rotations (each keyframe's last estimate).
        t_wc: ``(C, 3)`` final optical centres.
        R_wc_online: ``(C, 3, 3)`` each keyframe's pose right after its own fusion.
        t_wc_online: ``(C, 3)``.
        X_w: ``(P, 3)`` points (NaN where never triangulated).
        triangulated: ``(P,)`` bool.
        active: ``(M,)`` bool, observations still used (not rejected as outliers).
        records: one :class:`KeyframeRecord` per processed keyframe.
        seconds: total wall time.
    """

    method: str
    R_wc: np.ndarray
    t_wc: np.ndarray
    R_wc_online: np.ndarray
    t_wc_online: np.ndarray
    X_w: np.ndarray
    triangulated: np.ndarray
    active: np.ndarray
    records: list[KeyframeRecord] = field(default_factory=list)
    seconds: float = 0.0


class BaselineLengthFactor:
    """Length of the baseline between two cameras (the scale MPC's epipolar rows cannot see).

    Row per pair ``(i, j)``: ``r = (||T_j - T_i|| - L_hat) / sigma`` (``k = 1``, ``a = 2``), with
    ``dr/dT_j = u^T / sigma``, ``dr/dT_i = -u^T / sigma``, ``u = (T_j - T_i) / ||T_j - T_i||``
    and no rotation dependence. It only fills the off-diagonal blocks of successive cameras,
    like the pose-graph terms (fig. 3.3).

    Args:
        pairs: ``(Q, 2)`` state camera indices.
        lengths: ``(Q,)`` reference lengths ``L_hat`` (metres).
        sigma: metres, scalar or ``(Q,)``.
    """

    def __init__(self, pairs: np.ndarray, lengths: np.ndarray, sigma: float) -> None:
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        self.lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
        if self.lengths.shape != (self.pairs.shape[0],):
            raise SlamError("lengths: expected one per pair")
        if not np.all(np.asarray(sigma) > 0):
            raise SlamError(f"sigma: expected > 0, got {sigma}")
        self.sigma = np.asarray(sigma, dtype=np.float64)
        self.name = "baseline_length"

    @classmethod
    def from_state(cls, state, pairs: np.ndarray, sigma: float) -> BaselineLengthFactor:
        """``L_hat`` = the lengths at ``state`` (the pre-fusion estimate)."""
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        d = state.t_wc[pairs[:, 1]] - state.t_wc[pairs[:, 0]]
        return cls(pairs, np.linalg.norm(d, axis=1), sigma)

    @property
    def num_residuals(self) -> int:
        """One per pair."""
        return self.pairs.shape[0]

    def _r(self, state) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = state.t_wc[self.pairs[:, 1]] - state.t_wc[self.pairs[:, 0]]
        n = np.linalg.norm(d, axis=1)
        return (n - self.lengths) / self.sigma, d, n

    def _rows(self, state) -> tuple[np.ndarray, np.ndarray]:
        """``r (Q,)`` and ``J (Q, 12)`` = ``[d/d(dw_i, dT_i) | d/d(dw_j, dT_j)]``."""
        r, d, n = self._r(state)
        u = d / (np.maximum(n, 1e-12) * self.sigma)[:, None]
        J = np.zeros((r.size, 12))
        J[:, 3:6] = -u
        J[:, 9:12] = u
        return r, J

    def evaluate(self, state):
        """Rows ``(Q, 1)``, ``a = 2``."""
        from slam_bridge.factors.base import FactorBlock

        r, J = self._rows(state)
        return FactorBlock(r[:, None], self.pairs, J.reshape(-1, 2, 1, 6), name=self.name)

    def _normal_equations(self, state, cmap: np.ndarray, pmap: np.ndarray, Cf: int, Pf: int):
        """Compiled shortcut of :func:`slam_bridge.problem.assemble` (numba only): the per-pair
        products ``J^T J``, ``J^T r`` of the one-row pairs, scattered by
        :func:`slam_bridge.problem.pair_normal_equations` (the generic path's per-family
        overhead was ~0.2 ms per assembly for ~30 rows)."""
        from slam_bridge.problem import pair_normal_equations

        if type(self).evaluate is not BaselineLengthFactor.evaluate:
            return None
        r, J = self._rows(state)
        H = J[:, :, None] * J[:, None, :]
        cost = float(np.sum(r * r))
        return pair_normal_equations(cost, 0, H, J * r[:, None], self.pairs, cmap, Cf, Pf)

    def cost(self, state) -> float:
        """``sum r^2``."""
        return float(np.sum(self._r(state)[0] ** 2))

    def cost_and_invalid(self, state) -> tuple[float, int]:
        """``(cost, 0)``."""
        return self.cost(state), 0


def hessian_bytes(problem) -> int:
    """Memory of the assembled system of ``zeta`` for a hybrid problem (module docstring).

    Args:
        problem: a :class:`slam_bridge.window.HybridProblem` (its state's fixed masks count).

    Returns:
        ``8 (36 Cf + 36 Q + 18 N_W + 9 Pf)`` bytes.
    """
    st = problem.state
    cmap, pmap = st.camera_index_map, st.point_index_map
    Cf, Pf = int(st.free_cameras.size), int(st.free_points.size)
    reps = [f for f in problem.vision if isinstance(f, ReprojectionFactor)]
    c = cmap[np.concatenate([f.cameras for f in reps])]
    p = pmap[np.concatenate([f.points for f in reps])]
    keep = (c >= 0) & (p >= 0)
    n_w = int(np.unique(c[keep] * max(Pf, 1) + p[keep]).size)
    q = 0
    if problem.window.pose_graph_pairs.shape[0]:
        idx = {int(k): i for i, k in enumerate(problem.camera_ids)}
        for a, b in problem.window.pose_graph_pairs:
            if cmap[idx[int(a)]] >= 0 and cmap[idx[int(b)]] >= 0:
                q += 1
    return 8 * (36 * Cf + 36 * q + 18 * n_w + 9 * Pf)


def _pose_graph_references(
    problem,
    links: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]],
    link_info: dict[tuple[int, int], np.ndarray],
    D: np.ndarray,
    cfg: PipelineConfig,
) -> None:
    """Record ``S_hat`` of new pose-graph links; rebuild the pose-graph terms on the frozen
    references and the links' entry information.

    A link ``(z_i, z_{i+1})`` enters the pose graph when ``z_i`` leaves the BA window; its
    relative pose at that moment (eq. 3.2, the last estimate before this keyframe's k-BA and
    fusion) is stored. With ``freeze_links`` every later keyframe keeps that ``S_hat`` instead
    of re-taking it from the current, already fused, poses: otherwise each fusion's bend of the
    chain becomes the next keyframe's reference and the bends accumulate over the ``n``
    keyframes a camera spends in the pose graph. It applies to the DPC terms, MPC's baseline
    lengths and MPC's epipolar offsets (their rest position is the chain rebuilt from ``z_0``
    with the frozen relative poses, :func:`_frozen_chain_state`). DPC links with an entry
    information (``link_info``, :func:`_entry_information`) are weighed by it, the others by
    the constant ``D``.
    """
    from slam_bridge.factors.pose_graph_mpc import MPCFactor

    pg = problem.window.pose_graph_pairs
    st = problem.state
    for a, b in pg:
        key = (int(a), int(b))
        if key not in links:
            i, j = problem.camera_index(a), problem.camera_index(b)
            R_i = st.R_wc[i]
            links[key] = (R_i.T @ st.R_wc[j], R_i.T @ (st.t_wc[j] - st.t_wc[i]))
    if not pg.size:
        return
    ids = problem.camera_ids
    D_const = np.diag(D) if D.ndim == 1 else D
    for i, f in enumerate(problem.vision):
        if isinstance(f, DPCFactor) and (cfg.freeze_links or link_info):
            kp = [(int(ids[a]), int(ids[b])) for a, b in f.pairs]
            R_h, t_h = f.R_hat_ij, f.t_hat_ij
            if cfg.freeze_links:
                R_h = np.stack([links[q][0] for q in kp])
                t_h = np.stack([links[q][1] for q in kp])
            W = np.stack([link_info.get(q, D_const) for q in kp])
            problem.vision[i] = DPCFactor(f.pairs, R_h, t_h, W, kernel=f.kernel, name=f.name)
        elif isinstance(f, MPCFactor) and cfg.freeze_links and f.offset is not None:
            problem.vision[i] = f.relative_to(_frozen_chain_state(problem, links))


def _frozen_chain_state(problem, links: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]):
    """``problem.state`` with the pose-graph chain rebuilt from ``z_0`` (or ``z_1``) by the
    frozen relative poses: every link's relative pose is its ``S_hat`` there."""
    st = problem.state
    R, t = st.R_wc.copy(), st.t_wc.copy()
    for a, b in problem.window.pose_graph_pairs:
        i, j = problem.camera_index(a), problem.camera_index(b)
        R_h, t_h = links[(int(a), int(b))]
        R[j], t[j] = R[i] @ R_h, R[i] @ t_h + t[i]
    return dataclasses.replace(st, R_wc=R, t_wc=t)


def _camera_covariance(problem) -> np.ndarray | None:
    """``S^-1`` of ``problem``'s undamped vision system (eq. 1.32), ``(6 Cf, 6 Cf)``, or None
    when it cannot be factorised (logged)."""
    from slam_bridge.problem import assemble
    from slam_bridge.solvers.schur import SchurFactorization

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


def _entry_information(problem, cfg: PipelineConfig) -> tuple[tuple[int, int], np.ndarray] | None:
    """Weight of the link the pose graph gains at the next keyframe (``kba_window="hybrid"``).

    That link is the BA window's first pair ``(z_{n+1}, z_{n+2})``; ``z_{n+1}`` then leaves the
    BA window with its points. The information this window (at its optimum ``X*``, undamped
    normal equations, eq. 1.32) has on the pair's relative pose is what those points and rows
    gave it (:func:`slam_bridge.factors.pose_graph_dpc.relative_pose_information`), times
    ``dpc_info_scale``; the link keeps it while it stays in the pose graph.

    Returns:
        ``((id_{n+1}, id_{n+2}), D (6, 6))`` or None (fewer than 2 BA cameras, a fixed camera,
        or a system that cannot be factorised: the link then gets the constant ``D``).
    """
    from slam_bridge.factors.pose_graph_dpc import relative_pose_information

    ba = problem.window.ba_cameras
    if ba.size < 2:
        return None
    st = problem.state
    ia, ib = problem.camera_index(ba[0]), problem.camera_index(ba[1])
    fa, fb = int(st.camera_index_map[ia]), int(st.camera_index_map[ib])
    if fa < 0 or fb < 0:
        return None
    cov = _camera_covariance(problem)
    if cov is None:
        return None
    idx = np.r_[6 * fa : 6 * fa + 6, 6 * fb : 6 * fb + 6]
    cov_pair = cov[np.ix_(idx, idx)][None]
    R, t = st.R_wc[[ia, ib]], st.t_wc[[ia, ib]]
    info = relative_pose_information(
        R[:1], t[:1], R[1:], t[1:], cov_pair, min_sigma=cfg.dpc_min_sigma
    )
    return (int(ba[0]), int(ba[1])), cfg.dpc_info_scale * info[0]


def _link_information(kba, problem, cfg: PipelineConfig) -> int:
    """Weigh every DPC link of ``problem`` by its relative pose's information in the k-BA.

    The k-BA (``kba``, at its optimum, plain window of the ``l`` latest keyframes) sees the
    points the hybrid window drops; the covariance of its free cameras is ``S^-1`` (eq. 1.32,
    reduced camera system of its undamped normal equations). For each link ``(z_i, z_{i+1})``
    the joint ``12 x 12`` block (zero for a camera the k-BA holds fixed or does not hold, e.g.
    ``z_0``) gives ``D_i = Sigma_q^-1`` (:func:`slam_bridge.factors.pose_graph_dpc.
    relative_pose_information`), times ``dpc_info_scale``. A constant ``D`` is isotropic, while
    a link is stiff across the optical axis and soft along the baseline (scale) and the
    bas-relief directions: the fusion then bends the chain where the k-BA's points would
    have charged most, and the chain swings about ``z_0``. The factors are rebuilt in place
    (same ``S_hat``); when the k-BA's system cannot be factorised the constant ``D`` stays
    (logged).

    Returns:
        The number of links reweighed.
    """
    from slam_bridge.factors.pose_graph_dpc import relative_pose_information

    idx = [i for i, f in enumerate(problem.vision) if isinstance(f, DPCFactor)]
    if not idx:
        return 0
    st = kba.state
    cov = _camera_covariance(kba)
    if cov is None:  # constant D kept
        return 0
    cmap = st.camera_index_map
    free_of = {int(c): int(cmap[i]) for i, c in enumerate(kba.camera_ids)}
    ids = problem.camera_ids
    n = 0
    for i in idx:
        f = problem.vision[i]
        Q = f.pairs.shape[0]
        J = np.zeros((Q, 12, 12))
        for q, (a, b) in enumerate(f.pairs):
            fr = [free_of.get(int(ids[a]), -1), free_of.get(int(ids[b]), -1)]
            for u, fu in enumerate(fr):
                for v, fv in enumerate(fr):
                    if fu >= 0 and fv >= 0:
                        J[q, 6 * u : 6 * u + 6, 6 * v : 6 * v + 6] = cov[
                            6 * fu : 6 * fu + 6, 6 * fv : 6 * fv + 6
                        ]
        ps = problem.state
        a, b = f.pairs[:, 0], f.pairs[:, 1]
        D = cfg.dpc_info_scale * relative_pose_information(
            ps.R_wc[a], ps.t_wc[a], ps.R_wc[b], ps.t_wc[b], J, min_sigma=cfg.dpc_min_sigma
        )
        g = DPCFactor(f.pairs, f.R_hat_ij, f.t_hat_ij, D, kernel=f.kernel, name=f.name)
        if cfg.dpc_info_calibrate:
            scale = _chain_scale(g, problem, cov, free_of)
            if scale is not None:
                g = DPCFactor(
                    f.pairs, f.R_hat_ij, f.t_hat_ij, scale * D, kernel=f.kernel, name=f.name
                )
        problem.vision[i] = g
        n += Q
    return n


def _chain_scale(
    factor: DPCFactor, problem, cov_kba: np.ndarray, free_of: dict[int, int]
) -> float | None:
    """Factor on a DPC chain's weights that matches its end's covariance to the k-BA's.

    With the chain's own normal equations ``H = sum J^T J`` (whitened Jacobians, the chain's
    free cameras; its fixed first camera ``z_0`` is the gauge), the translation covariance of
    the newest camera of the last pair is ``tr_c = tr (H^-1)_TT``; the k-BA's is ``tr_k`` (its
    ``S^-1`` block, ``cov_kba``). Scaling every weight by ``tr_c / tr_k`` makes the two equal.

    Args:
        factor: the DPC family (pairs in time order, ``(z_0, z_1) ... (z_n, z_{n+1})``).
        problem: the hybrid window.
        cov_kba: ``(6 Cf_kba, 6 Cf_kba)`` covariance of the k-BA's free cameras.
        free_of: keyframe id -> free index in the k-BA (``-1``: fixed).

    Returns:
        The factor, clipped to ``[1, 1e4]``, or None when the chain has no fixed camera, its
        end is not free in the k-BA, or its system is singular.
    """
    st = problem.state
    cmap = st.camera_index_map
    cams = np.unique(factor.pairs)
    free = [int(c) for c in cams if cmap[c] >= 0]
    end = int(factor.pairs[-1, 1])
    fk = free_of.get(int(problem.camera_ids[end]), -1)
    if len(free) == cams.size or end not in free or fk < 0:
        return None
    loc = {c: i for i, c in enumerate(free)}
    blk = factor.evaluate(st)
    H = np.zeros((6 * len(free), 6 * len(free)))
    for q, (a, b) in enumerate(factor.pairs):
        js = [(loc.get(int(c)), blk.J_cameras[q, s]) for s, c in enumerate((a, b))]
        for ia, Ja in js:
            for ib, Jb in js:
                if ia is not None and ib is not None:
                    H[6 * ia : 6 * ia + 6, 6 * ib : 6 * ib + 6] += Ja.T @ Jb
    try:
        C = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    e = 6 * loc[end] + 3
    tr_c = float(np.trace(C[e : e + 3, e : e + 3]))
    tr_k = float(np.trace(cov_kba[6 * fk + 3 : 6 * fk + 6, 6 * fk + 3 : 6 * fk + 6]))
    if not (np.isfinite(tr_c) and tr_k > 0):
        return None
    return float(np.clip(tr_c / tr_k, 1.0, 1e4))


def _bad_row_share(rep, state, threshold_px: float) -> float:
    """Share of the rows of a reprojection family erring by more than ``threshold_px`` (or
    invalid) at ``state`` (residuals are pixels over ``rep.sigma``)."""
    r, ok = rep.residuals(state)
    err = np.linalg.norm(r, axis=1) * rep.sigma
    return float(np.mean(~ok | (err > threshold_px))) if r.shape[0] else 0.0


def _add_length_terms(
    problem,
    kind: str,
    cfg: PipelineConfig,
    links: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]],
) -> None:
    """Append the :class:`BaselineLengthFactor` terms of ``mpc_length_sigma_m`` (pose-graph
    pairs, MPC) and ``ba_scale_sigma_m`` (first BA-window pair) to ``problem.vision``."""
    st = problem.state
    pairs, sig, lengths = [], [], []
    if kind == "mpc" and cfg.mpc_length_sigma_m:
        for a, b in problem.window.pose_graph_pairs:
            i, j = problem.camera_index(a), problem.camera_index(b)
            pairs.append((i, j))
            sig.append(cfg.mpc_length_sigma_m)
            if cfg.freeze_links:
                lengths.append(float(np.linalg.norm(links[(int(a), int(b))][1])))
            else:
                lengths.append(float(np.linalg.norm(st.t_wc[j] - st.t_wc[i])))
    ba = problem.window.ba_cameras
    if cfg.ba_scale_sigma_m and ba.size >= 2:
        i, j = problem.camera_index(ba[0]), problem.camera_index(ba[1])
        pairs.append((i, j))
        sig.append(cfg.ba_scale_sigma_m)
        lengths.append(float(np.linalg.norm(st.t_wc[j] - st.t_wc[i])))
    if pairs:
        problem.vision.append(
            BaselineLengthFactor(np.array(pairs), np.array(lengths), np.array(sig))
        )


def _hybrid_problem(
    data: SequenceData,
    cfg: PipelineConfig,
    kind: str,
    D: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    keyframes: np.ndarray,
    sel: np.ndarray,
    l_eff: int,
    n_eff: int,
    k: int,
):
    """The hybrid window of keyframe ``k`` (eq. 3.4) over the observations ``sel``.

    The pose-graph keyframes' observations (MPC's correspondences, the ``pose_graph_rows``) are
    thinned to the ``pose_graph_share`` ``s`` of the points (by point id), keyframes left with
    fewer than 40 observations keeping them all; if the thinned window is invalid the full one
    is used. The kept rows' pixel sigma is multiplied by ``sqrt(s)``: each kept row stands for
    the ``1 / s`` it represents, so the chain and its tie to the BA window are about as stiff as
    with all of them (MPC, measured on 160 m, sigma_b = 0.75 m: 3.5 % inlier loss vs 8.8 % with
    sigma 1 px, same time).

    Returns:
        ``(observations used, problem)``.
    """
    obs = data.observations
    kf_obs, pt_obs, uv = obs.keyframe, obs.point, obs.uv
    sel_all = sel
    share = cfg.pose_graph_share
    thinned = (kind == "mpc" or cfg.pose_graph_rows) and share < 1.0
    if thinned:
        pg_end = k + 1 - (l_eff - n_eff)
        in_pg = kf_obs[sel] < pg_end
        h = (pt_obs[sel] * 2654435761) % 1000
        thin = in_pg & (h >= 1000 * share)
        left = np.bincount(kf_obs[sel][~thin], minlength=k + 1)
        thin &= left[kf_obs[sel]] >= 40
        sel = sel[~thin]
    wcfg = HybridWindowConfig(
        l=cfg.l,
        n=n_eff,
        pose_graph=kind,
        D=D,
        mpc_sigma=cfg.mpc_sigma_px * (np.sqrt(share) if thinned else 1.0),
        mpc_relative=cfg.mpc_relative,
        pose_graph_rows=cfg.pose_graph_rows,
        pose_graph_row_sigma=float(np.sqrt(share)) if thinned and cfg.pose_graph_rows else None,
        reprojection_kernel=cfg.reprojection_kernel,
        reprojection_kernel_scale=cfg.reprojection_kernel_px,
    )
    try:
        problem = build_hybrid_problem(
            R_wc, t_wc, X_w, data.K, keyframes, kf_obs[sel], pt_obs[sel], uv[sel], wcfg
        )
    except WindowError:
        if sel_all is sel:
            raise
        logger.debug("keyframe %d: MPC window without thinning", k)
        sel = sel_all
        wcfg = dataclasses.replace(wcfg, mpc_sigma=cfg.mpc_sigma_px, pose_graph_row_sigma=None)
        problem = build_hybrid_problem(
            R_wc, t_wc, X_w, data.K, keyframes, kf_obs[sel], pt_obs[sel], uv[sel], wcfg
        )
    return sel, problem


def _carry_points(
    obs_points: np.ndarray,
    obs_keyframes: np.ndarray,
    fused_points: np.ndarray,
    pg_ids: np.ndarray,
    R_ref: np.ndarray,
    t_ref: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
) -> np.ndarray:
    """Move the points only the pose-graph cameras see along with their newest observer.

    The hybrid fusion moves the pose-graph cameras ``pg_ids`` (from ``R_ref, t_ref``, their
    k-BA poses, to the fused ``R_wc, t_wc``) without the points that left the problem (eq.
    3.4): left in place they would contradict the fused cameras, and the next k-BA would pull
    the cameras back toward them, undoing the GPS correction. Each such point is carried
    rigidly by its newest pose-graph observer ``c``:
    ``X <- R_c R_ref_c^T (X - t_ref_c) + t_c`` (its coordinates in that camera are kept).
    Not in the thesis (which does not say what becomes of those points); ``n = 0`` never calls
    it.

    Returns:
        ``(M,)`` ids of the points moved (``X_w`` is updated in place).
    """
    in_pg = np.isin(obs_keyframes, pg_ids) & ~np.isin(obs_points, fused_points)
    if not np.any(in_pg):
        return np.zeros(0, dtype=np.int64)
    pts, kfs = obs_points[in_pg], obs_keyframes[in_pg]
    newest = np.full(X_w.shape[0], -1, dtype=np.int64)
    np.maximum.at(newest, pts, kfs)
    moved = np.unique(pts)
    c = np.searchsorted(pg_ids, newest[moved])
    X_c = np.einsum("mba,mb->ma", R_ref[c], X_w[moved] - t_ref[c])
    X_w[moved] = np.einsum("mab,mb->ma", R_wc[pg_ids[c]], X_c) + t_wc[pg_ids[c]]
    return moved


def _refine_points(
    data: SequenceData,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    active: np.ndarray,
    upto: int,
    points: np.ndarray,
) -> int:
    """Re-triangulate ``points`` from all their active observations with the current poses.

    The points that left the hybrid window are only carried rigidly (:func:`_carry_points`)
    while the pose graph bends under later fusions, so the stored map drifts from what its
    cameras see (measured, 640 m, sigma_b = 0.75 m, DPC: half of the stored points erred by
    2 px or more somewhere). The loop refits them once, after its last keyframe, with the
    final poses (``refine_left_points``). A point takes its refit (DLT + Gauss-Newton,
    :func:`slam_bridge.geometry.triangulate`) only when that lowers its worst reprojection
    error.

    Args:
        upto: the first ``upto`` observations count (data order, by keyframe: ``starts[C]``
            for all of ``C`` keyframes).
        points: ``(M,)`` point ids.

    Returns:
        The number of points updated (``X_w`` in place).
    """
    obs = data.observations
    if points.size == 0:
        return 0
    o = np.arange(upto)
    o = o[active[o] & np.isin(obs.point[o], points)]
    if o.size == 0:
        return 0
    pts_u, local = np.unique(obs.point[o], return_inverse=True)
    kf = obs.keyframe[o]
    res = triangulate(
        data.K, R_wc, t_wc, kf, local, obs.uv[o], num_points=pts_u.size, min_parallax_deg=0.0
    )

    def worst_error(X: np.ndarray) -> np.ndarray:
        uv_hat, _, front = project(data.K, R_wc[kf], t_wc[kf], np.nan_to_num(X[local]))
        err = np.where(
            front, np.linalg.norm(np.nan_to_num(uv_hat - obs.uv[o], nan=1e9), axis=1), 1e9
        )
        worst = np.zeros(pts_u.size)
        np.maximum.at(worst, local, err)
        return worst

    better = res.valid & (worst_error(res.X_w) < worst_error(X_w[pts_u]))
    X_w[pts_u[better]] = res.X_w[better]
    return int(better.sum())


def _plain_kba(
    data: SequenceData,
    cfg: PipelineConfig,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    keyframes: np.ndarray,
    sel: np.ndarray,
    l: int,
    k: int,
    iterations: int,
):
    """The plain (``n = 0``) k-BA of the ``l`` latest keyframes over the observations ``sel``,
    minimised by ``iterations`` LM iterations, the anchor keyframes held fixed.

    Returns:
        ``(problem at its optimum, the LM result)``.
    """
    obs = data.observations
    kba = build_hybrid_problem(
        R_wc, t_wc, X_w, data.K, keyframes, obs.keyframe[sel], obs.point[sel], obs.uv[sel],
        HybridWindowConfig(
            l=l, n=0,
            reprojection_kernel=cfg.reprojection_kernel,
            reprojection_kernel_scale=cfg.reprojection_kernel_px,
        ),
    )  # fmt: skip
    kba.state.camera_fixed[kba.camera_ids < cfg.anchor_keyframes] = True
    if kba.state.free_cameras.size == 0:
        raise SlamError(f"keyframe {k}: the window has no free camera")
    return minimize_zeta(kba, LMConfig(max_iterations=iterations))


def _forget_links(links: dict, link_info: dict, first: int) -> None:
    """Drop the frozen references (and DPC weights) of the links ending at keyframe ``first``
    or later: a plain k-BA moved those cameras, the hybrid re-takes them when it resumes."""
    for key in [q for q in links if q[1] >= first]:
        del links[key]
        link_info.pop(key, None)


def _window_n(method: str, cfg: PipelineConfig, l_eff: int) -> int:
    if not METHODS[method][1]:
        return 0
    return max(0, min(cfg.n, l_eff - (cfg.l - cfg.n)))


def run_pipeline(
    data: SequenceData,
    method: str = "ba",
    config: PipelineConfig | None = None,
    *,
    num_keyframes: int | None = None,
) -> PipelineResult:
    """Process a sequence keyframe by keyframe (module docstring).

    Args:
        data: the sequence.
        method: ``ba`` (``n = 0``, Lhuillier's barrier BA), ``dpc`` or ``mpc`` (hybrid).
        config: loop settings.
        num_keyframes: process only the first keyframes (default all).

    Returns:
        A :class:`PipelineResult`.

    Raises:
        SlamError: unknown method, too few keyframes, tracking lost (too few PnP matches), a
            non-finite estimate (never returned silently).
    """
    if method not in METHODS:
        raise SlamError(f"method: expected one of {sorted(METHODS)}, got {method!r}")
    cfg = config or PipelineConfig()
    if cfg.blas_threads is None:
        return _run_pipeline(data, method, cfg, num_keyframes)
    with threadpool_limits(limits=cfg.blas_threads, user_api="blas"):
        return _run_pipeline(data, method, cfg, num_keyframes)


def _run_pipeline(
    data: SequenceData, method: str, cfg: PipelineConfig, num_keyframes: int | None
) -> PipelineResult:
    """:func:`run_pipeline` under its BLAS thread limit."""
    t_start = time.perf_counter()
    C = data.num_keyframes if num_keyframes is None else min(num_keyframes, data.num_keyframes)
    if C < cfg.anchor_keyframes + 1:
        raise SlamError(
            f"the sequence has {C} keyframes; at least {cfg.anchor_keyframes + 1} are needed "
            "(anchors + one tracked keyframe)"
        )
    obs = data.observations
    K = data.K
    kf_obs, pt_obs, uv = obs.keyframe, obs.point, obs.uv
    starts = np.searchsorted(kf_obs, np.arange(C + 1))
    P = int(data.num_points)
    R_wc = np.repeat(np.eye(3)[None], data.num_keyframes, axis=0)
    t_wc = np.zeros((data.num_keyframes, 3))
    R_on, t_on = R_wc.copy(), t_wc.copy()
    X_w = np.full((P, 3), np.nan)
    tri_ok = np.zeros(P, dtype=bool)
    active = np.ones(kf_obs.size, dtype=bool)
    anchors = np.arange(cfg.anchor_keyframes)
    R_wc[anchors] = data.R_wc_true[anchors]
    t_wc[anchors] = data.t_wc_true[anchors]
    R_on[anchors], t_on[anchors] = R_wc[anchors], t_wc[anchors]
    kind, _ = METHODS[method]
    D = np.concatenate(
        [np.full(3, cfg.dpc_sigma_rot_rad**-2), np.full(3, cfg.dpc_sigma_trans_m**-2)]
    )
    links: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    link_info: dict[tuple[int, int], np.ndarray] = {}
    left = np.zeros(P, dtype=bool)  # points that left a hybrid window (carried)
    records: list[KeyframeRecord] = []
    tracked = np.full(data.num_keyframes, np.iinfo(np.int64).max)  # PnP inliers per keyframe
    n0 = _triangulate_new(
        data, cfg, R_wc, t_wc, X_w, tri_ok, active, starts, cfg.anchor_keyframes - 1
    )
    logger.debug("%s: %d points from the anchors", method, n0)
    for k in range(cfg.anchor_keyframes, C):
        rec = KeyframeRecord(keyframe=k)
        sl = np.arange(starts[k], starts[k + 1])
        # 1. tracking
        trk = sl[active[sl] & tri_ok[pt_obs[sl]]]
        if trk.size < cfg.min_tracked:
            raise SlamError(
                f"tracking lost at keyframe {k}: {trk.size} observations of mapped points, "
                f"fewer than {cfg.min_tracked}"
            )
        R_k, t_k, n_in = _track(K, X_w[pt_obs[trk]], uv[trk], R_wc, t_wc, k, cfg)
        if n_in < 6:
            raise SlamError(
                f"tracking lost at keyframe {k}: {n_in} PnP inliers among {trk.size} "
                f"observations of mapped points (at least 6 needed)"
            )
        if n_in < cfg.min_tracked:  # weak: keep the pose, let the k-BA decide, gate nothing
            logger.warning("keyframe %d: weak tracking (%d PnP inliers)", k, n_in)
        else:
            uv_hat, _, front = project(K, R_k, t_k, X_w[pt_obs[trk]])
            err = np.where(
                front, np.linalg.norm(np.nan_to_num(uv_hat - uv[trk], nan=1e9), axis=1), 1e9
            )
            active[trk[err > cfg.outlier_gate_px]] = False
        rec.n_tracked = tracked[k] = int(n_in)
        R_wc[k], t_wc[k] = R_k, t_k
        # 2. mapping
        rec.n_new_points = _triangulate_new(data, cfg, R_wc, t_wc, X_w, tri_ok, active, starts, k)
        # 3. the SLAM's k-BA: plain (n = 0) window of the l latest keyframes, for every method
        first = max(0, k + 1 - cfg.l - cfg.history_keyframes)
        keyframes = np.arange(first, k + 1)
        l_eff = min(cfg.l, k + 1)
        n_eff = _window_n(method, cfg, l_eff)
        if n_eff > 0 and cfg.weak_track_inliers is not None:
            span = l_eff - n_eff if cfg.weak_track_span is None else cfg.weak_track_span
            weakest = int(tracked[max(0, k + 1 - span) : k + 1].min())
            if weakest < cfg.weak_track_inliers:
                n_weak = min(cfg.weak_track_n, n_eff)
                logger.info(
                    "keyframe %d: %s window holds a keyframe tracked with %d PnP inliers: "
                    "k-BA with n = %d, the links of the cameras back in the BA window re-taken",
                    k, method, weakest, n_weak,
                )  # fmt: skip
                _forget_links(links, link_info, k + 1 - l_eff + n_weak)
                rec.fallback = True
                n_eff = n_weak
        lo = starts[first]
        sel = lo + np.flatnonzero(active[lo : starts[k + 1]] & tri_ok[pt_obs[lo : starts[k + 1]]])
        t0 = time.perf_counter()
        kba = None
        if n_eff == 0 or cfg.kba_window in ("plain", "ba"):
            l_kba = cfg.l if (n_eff == 0 or cfg.kba_window == "plain") else l_eff - n_eff
            kba, lm = _plain_kba(
                data, cfg, R_wc, t_wc, X_w, keyframes, sel, l_kba, k, cfg.ba_iterations
            )
            rec.ba_iterations = int(lm.iterations)
            problem = kba
            if n_eff > 0:  # S_hat (eq. 3.14) = the relative poses after this k-BA
                kba.write_back(kba.state, R_wc, t_wc, X_w)
        # 3b. hybrids: the fusion's zeta (eq. 3.4) and X* = argmin zeta, from the k-BA's poses
        sel_window = sel
        if n_eff > 0:
            pg_ids = np.arange(k + 1 - l_eff, k + 1 - l_eff + n_eff)
            R_ref, t_ref = R_wc[pg_ids].copy(), t_wc[pg_ids].copy()
            sel, problem = _hybrid_problem(
                data, cfg, kind, D, R_wc, t_wc, X_w, keyframes, sel, l_eff, n_eff, k
            )
            problem.state.camera_fixed[np.isin(problem.camera_ids, anchors)] = True
            _pose_graph_references(problem, links, link_info, D, cfg)
            if cfg.dpc_weight == "information" and kba is not None and kind == "dpc":
                _link_information(kba, problem, cfg)
            _add_length_terms(problem, kind, cfg, links)
            if problem.state.free_cameras.size == 0:
                raise SlamError(f"keyframe {k}: the window has no free camera")
            it = cfg.zeta_iterations if kba is not None else cfg.ba_iterations
            problem, lm = minimize_zeta(problem, LMConfig(max_iterations=it))
            rec.ba_iterations += int(lm.iterations)
            misfit = (
                _bad_row_share(problem.vision[0], problem.state, cfg.consistency_px)
                if cfg.consistency_share is not None
                else 0.0
            )
            if cfg.consistency_share is not None and misfit > cfg.consistency_share:
                logger.warning(
                    "keyframe %d: %s window inconsistent (%.1f %% of its BA-window rows over "
                    "%.0f px at X*): plain k-BA (n = 0) for this keyframe, its links re-taken",
                    k, method, 100 * misfit, cfg.consistency_px,
                )  # fmt: skip
                _forget_links(links, link_info, int(pg_ids[0]))
                sel = sel_window
                problem, lm = _plain_kba(
                    data, cfg, R_wc, t_wc, X_w, keyframes, sel, cfg.l, k,
                    cfg.consistency_iterations,
                )  # fmt: skip
                rec.ba_iterations += int(lm.iterations)
                rec.fallback = True
                n_eff = 0
            elif kba is None and kind == "dpc" and cfg.dpc_weight == "information":
                got = _entry_information(problem, cfg)
                if got is not None:
                    link_info[got[0]] = got[1]
        rec.ba_seconds = time.perf_counter() - t0
        st = problem.state
        rec.n_pose_graph = n_eff
        rec.n_cameras = int(st.free_cameras.size)
        rec.n_points = int(st.free_points.size)
        rec.hessian_bytes = hessian_bytes(problem)
        state = problem.state
        # 4. fusion
        gps = data.gps_xy[k]
        if cfg.fuse and np.all(np.isfinite(gps)):
            factor = GPSFactor.most_recent(state, gps, weight=cfg.gps_weight)
            bcfg = BarrierConfig(
                t_ratio=cfg.t_ratio,
                gamma_rel=cfg.gamma_rel,
                max_iterations=cfg.fusion_iterations,
                max_backtracks=cfg.fusion_backtracks,
            )
            t0 = time.perf_counter()
            fused = solve_barrier(problem.vision, [factor], state, bcfg)
            rec.fusion_seconds = time.perf_counter() - t0
            rec.fusion_iterations = int(fused.iterations)
            rec.fusion_seconds_per_iteration = float(fused.seconds_per_iteration)
            rec.zeta_star, rec.zeta = float(fused.zeta_star), float(fused.zeta)
            rec.gps_used = True
            if cfg.fusion_guard_share is not None and n_eff > 0:
                rep = problem.vision[0]
                before = _bad_row_share(rep, state, cfg.fusion_guard_px)
                after = _bad_row_share(rep, fused.state, cfg.fusion_guard_px)
                if after - before > cfg.fusion_guard_share:
                    logger.warning(
                        "keyframe %d: fusion rejected (rows over %.1f px: %.1f %% -> %.1f %%); "
                        "X* kept",
                        k,
                        cfg.fusion_guard_px,
                        100 * before,
                        100 * after,
                    )
                    rec.gps_used = False
            if rec.gps_used:
                state = fused.state
        elif cfg.fuse:
            logger.debug("keyframe %d: no GPS fix (dropout), not fused", k)
        problem.write_back(state, R_wc, t_wc, X_w)
        if n_eff > 0:
            moved = _carry_points(
                pt_obs[sel_window], kf_obs[sel_window], problem.point_ids, pg_ids, R_ref,
                t_ref, R_wc, t_wc, X_w,
            )  # fmt: skip
            left[moved] = True
        if not (np.all(np.isfinite(t_wc[: k + 1])) and np.all(np.isfinite(R_wc[: k + 1]))):
            raise SlamError(f"keyframe {k}: non-finite pose estimate")
        R_on[k], t_on[k] = R_wc[k], t_wc[k]
        # 5. gating (the fusion window's reprojection rows)
        o = sel[problem.window.observations]
        uv_hat, _, front = project(K, R_wc[kf_obs[o]], t_wc[kf_obs[o]], X_w[pt_obs[o]])
        err = np.where(front, np.linalg.norm(np.nan_to_num(uv_hat - uv[o], nan=1e9), axis=1), 1e9)
        bad = o[err > cfg.window_gate_px]
        active[bad] = False
        if cfg.cull_degenerate_points:
            # every active view of the window's points, older ones included
            in_window = np.zeros(data.num_points, dtype=bool)
            in_window[pt_obs[o]] = True
            ok = np.flatnonzero(active[: starts[k + 1]] & in_window[pt_obs[: starts[k + 1]]])
            rec.n_culled = _cull_degenerate_points(
                pt_obs[ok], R_wc[kf_obs[ok]], t_wc[kf_obs[ok]], X_w, tri_ok, cfg.min_parallax_deg
            )
        records.append(rec)
        if k % 25 == 0:
            logger.info(
                "%s kf %d/%d: %d cams, %d pts, BA %.0f ms, fusion %d it %.0f ms",
                method,
                k,
                C - 1,
                rec.n_cameras,
                rec.n_points,
                1e3 * rec.ba_seconds,
                rec.fusion_iterations,
                1e3 * rec.fusion_seconds,
            )
    if cfg.refine_left_points and np.any(left):
        n_ref = _refine_points(data, R_wc, t_wc, X_w, active, starts[C], np.flatnonzero(left))
        logger.debug("%s: %d carried points re-triangulated with the final poses", method, n_ref)
    return PipelineResult(
        method=method,
        R_wc=R_wc[:C],
        t_wc=t_wc[:C],
        R_wc_online=R_on[:C],
        t_wc_online=t_on[:C],
        X_w=X_w,
        triangulated=tri_ok,
        active=active,
        records=records,
        seconds=time.perf_counter() - t_start,
    )


def _track(
    K: np.ndarray,
    X_w: np.ndarray,
    uv: np.ndarray,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    k: int,
    cfg: PipelineConfig,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Pose of keyframe ``k`` from 2D-3D matches: PnP, or the constant-velocity prediction
    ``(R_{k-1} R_{k-2}^T R_{k-1}, T_{k-1} + R_{k-1} R_{k-2}^T (T_{k-1} - T_{k-2}))`` refined by
    PnP's LM when RANSAC finds no consensus; the candidate with more inliers (error <
    ``pnp_threshold_px``) wins.

    Returns:
        ``R_wc (3, 3)``, ``t_wc (3,)``, number of inliers.
    """
    import cv2

    dR = R_wc[k - 1] @ R_wc[k - 2].T
    cands = [(dR @ R_wc[k - 1], t_wc[k - 1] + dR @ (t_wc[k - 1] - t_wc[k - 2]))]
    try:
        res = pnp(K, X_w, uv, threshold_px=cfg.pnp_threshold_px, seed=k)
        cands.append((res.R_wc, res.t_wc))
    except SlamError as exc:
        logger.debug("keyframe %d: PnP RANSAC failed (%s); motion model", k, exc)
    best = None
    for R, t in cands:
        for _ in range(2):  # score, then refine on the inliers (OpenCV LM)
            uv_hat, _, front = project(K, R, t, X_w)
            err = np.where(front, np.linalg.norm(np.nan_to_num(uv_hat - uv, nan=1e9), axis=1), 1e9)
            inl = err < cfg.pnp_threshold_px
            if inl.sum() < 6:
                break
            rvec = cv2.Rodrigues(np.ascontiguousarray(R.T))[0].reshape(3, 1)
            tvec = np.ascontiguousarray(-(R.T @ t)).reshape(3, 1)
            rvec, tvec = cv2.solvePnPRefineLM(
                np.ascontiguousarray(X_w[inl]), np.ascontiguousarray(uv[inl]), K, None, rvec, tvec
            )
            R_cw, _ = cv2.Rodrigues(rvec)
            R, t = R_cw.T, -(R_cw.T @ tvec.reshape(3))
        uv_hat, _, front = project(K, R, t, X_w)
        err = np.where(front, np.linalg.norm(np.nan_to_num(uv_hat - uv, nan=1e9), axis=1), 1e9)
        n_in = int(np.sum(err < cfg.pnp_threshold_px))
        if best is None or n_in > best[2]:
            best = (R, t, n_in)
    return best


def _cull_degenerate_points(
    points: np.ndarray,
    R_obs: np.ndarray,
    t_obs: np.ndarray,
    X_w: np.ndarray,
    tri_ok: np.ndarray,
    min_parallax_deg: float,
) -> int:
    """Untriangulate the points whose geometry the optimisation has made degenerate.

    A point triangulated with enough parallax can still slide along its rays in the k-BA or
    the fusion when its observers are few and close in direction (a sharp turn): the
    reprojection gate cannot see it (it still reprojects well), but the next keyframe's PnP
    does. A point whose observers' rays now meet at less than ``min_parallax_deg`` (the
    triangulation threshold), or that lies behind one of them, is marked untriangulated; the
    next keyframe that sees it triangulates it anew from all its active observations.

    Args:
        points: ``(M,)`` point id of each active observation of the points to check (all their
            views, not only the window's: old views carry the parallax).
        R_obs: ``(M, 3, 3)`` rotation of its keyframe.
        t_obs: ``(M, 3)`` optical centre of its keyframe.
        X_w: ``(P, 3)`` the map.
        tri_ok: ``(P,)`` triangulated flags (updated in place).
        min_parallax_deg: parallax threshold, degrees.

    Returns:
        The number of points untriangulated.
    """
    if points.size == 0:
        return 0
    uniq, local = np.unique(points, return_inverse=True)
    X_obs = X_w[points]
    parallax = ray_parallax_deg(t_obs, X_obs, local, uniq.size)
    depth = np.einsum("mi,mi->m", X_obs - t_obs, R_obs[:, :, 2])  # camera z axis in the world
    behind = np.zeros(uniq.size, dtype=bool)
    np.logical_or.at(behind, local, ~(depth > 0))
    views = np.bincount(local, minlength=uniq.size)
    # a point with a single active view left has nothing to measure parallax with: kept
    cull = tri_ok[uniq] & (behind | ((views >= 2) & (parallax < min_parallax_deg)))
    tri_ok[uniq[cull]] = False
    return int(cull.sum())


def _triangulate_new(
    data: SequenceData,
    cfg: PipelineConfig,
    R_wc: np.ndarray,
    t_wc: np.ndarray,
    X_w: np.ndarray,
    tri_ok: np.ndarray,
    active: np.ndarray,
    starts: np.ndarray,
    k: int,
) -> int:
    """Triangulate the untriangulated points seen by keyframe ``k`` (in place); returns count."""
    obs = data.observations
    sl = np.arange(starts[k], starts[k + 1])
    cand = np.unique(obs.point[sl][active[sl] & ~tri_ok[obs.point[sl]]])
    if cand.size == 0:
        return 0
    upto = np.arange(starts[k + 1])
    o = upto[active[upto] & np.isin(obs.point[upto], cand)]
    counts = np.bincount(obs.point[o], minlength=X_w.shape[0])
    o = o[counts[obs.point[o]] >= 2]
    if o.size == 0:
        return 0
    pts_u, local = np.unique(obs.point[o], return_inverse=True)
    res = triangulate(
        data.K,
        R_wc,
        t_wc,
        obs.keyframe[o],
        local,
        obs.uv[o],
        num_points=pts_u.size,
        min_parallax_deg=cfg.min_parallax_deg,
    )
    Xo = np.where(res.valid[:, None], res.X_w, 0.0)[local]
    uv_hat, _, front = project(data.K, R_wc[obs.keyframe[o]], t_wc[obs.keyframe[o]], Xo)
    err = np.where(front, np.linalg.norm(np.nan_to_num(uv_hat - obs.uv[o], nan=1e9), axis=1), 1e9)
    worst = np.zeros(pts_u.size)
    np.maximum.at(worst, local, err)
    good = res.valid & (worst <= cfg.outlier_gate_px)
    # a valid point with one bad observation: drop its worst observation, retry later
    bad_pt = res.valid & ~good
    if np.any(bad_pt):
        is_worst = bad_pt[local] & (err >= worst[local]) & (err > cfg.outlier_gate_px)
        active[o[is_worst]] = False
    X_w[pts_u[good]] = res.X_w[good]
    tri_ok[pts_u[good]] = True
    return int(good.sum())


# ------------------------------------------------------------------------------- experiment
@dataclass
class SequenceConfig:
    """The synthetic drive.

    Attributes:
        rig: ``car`` or ``tram``.
        length_m: distance driven (the thesis's synthetic sequence: 640 m).
        speed_mps: cruise speed (None: the rig's default).
        fps: frame rate of the drive.
        seed: route seed.
        image_size: ``(W, H)``.
        keyframe_spacing_m: a keyframe every this many metres driven.
    """

    rig: str = "car"
    length_m: float = 640.0
    speed_mps: float | None = None
    fps: float = 10.0
    seed: int = 0
    image_size: tuple[int, int] = (640, 480)
    keyframe_spacing_m: float = 2.0


def _default_world():
    from geoseg.synth.world import WorldConfig

    return WorldConfig()


@dataclass
class ExperimentConfig:
    """The chapter-3 experiment (``configs/slam_ch3.yaml``).

    Attributes:
        world: :class:`geoseg.synth.WorldConfig`.
        sequence: the drive.
        landmarks: points and measurement model.
        pipeline: the keyframe loop.
        methods: among ``ba``, ``dpc``, ``mpc``.
        gps_sigmas: sigma_b values (m) of the thesis's noise-only GPS (Table 3.1).
        gps_bias: add a run with :func:`geoseg.synth.gps.simulate_gps`'s locally constant bias,
            noise and dropouts (``gps`` settings).
        gps: the bias model of that run (``rate_hz`` is replaced by the frame rate).
        quick_length_m: sequence length of the default (non ``--full``) run.
        quick_sigmas: sigma_b values of the default run.
        quick_bias: whether the default run includes the bias setting.
        seed: seed of landmarks, noise and GPS.
    """

    world: object = field(default_factory=_default_world)
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    landmarks: LandmarkConfig = field(default_factory=LandmarkConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    methods: list[str] = field(default_factory=lambda: ["ba", "dpc", "mpc"])
    gps_sigmas: list[float] = field(default_factory=lambda: [0.0, 0.75, 1.5])
    gps_bias: bool = True
    gps: object = None
    quick_length_m: float = 160.0
    quick_sigmas: list[float] = field(default_factory=lambda: [0.75])
    quick_bias: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        from geoseg.config import from_dict
        from geoseg.synth.gps import GpsConfig
        from geoseg.synth.world import WorldConfig

        if isinstance(self.world, dict):
            self.world = from_dict(WorldConfig, self.world, where="world")
        if self.gps is None:
            self.gps = GpsConfig()
        elif isinstance(self.gps, dict):
            self.gps = from_dict(GpsConfig, self.gps, where="gps")
        unknown = sorted(set(self.methods) - set(METHODS))
        if unknown or not self.methods:
            raise SlamError(f"methods: expected some of {sorted(METHODS)}, got {self.methods}")
        if any(s < 0 for s in self.gps_sigmas):
            raise SlamError(f"gps_sigmas: expected values >= 0, got {self.gps_sigmas}")

    def quick(self) -> ExperimentConfig:
        """The default (short) run: ``quick_length_m`` and the quick GPS settings."""
        seq = dataclasses.replace(self.sequence, length_m=self.quick_length_m)
        return dataclasses.replace(
            self, sequence=seq, gps_sigmas=list(self.quick_sigmas), gps_bias=self.quick_bias
        )

    def settings(self) -> list[str]:
        """GPS setting names: ``sigma=0.75`` ... and ``bias``."""
        out = [f"sigma={s:g}" for s in self.gps_sigmas]
        return out + (["bias"] if self.gps_bias else [])


@dataclass
class Sequence:
    """A prepared sequence plus its scene (for plots).

    Attributes:
        data: the loop's input (``gps_xy`` is NaN: set per GPS setting).
        frames: ``(C,)`` trajectory frame index of each keyframe.
        trajectory: the full :class:`geoseg.synth.Trajectory`.
        num_outliers: gross outliers planted.
    """

    data: SequenceData
    frames: np.ndarray
    trajectory: object
    num_outliers: int


def make_sequence(cfg: ExperimentConfig) -> Sequence:
    """World, drive, keyframes, landmarks and observations of the experiment.

    Returns:
        A :class:`Sequence` (GPS not yet set).
    """
    from geoseg.synth import build_world, drive
    from slam_bridge.landmarks import (
        SceneCaster,
        sample_landmarks,
        simulate_observations,
        visible_observations,
    )

    world = build_world(cfg.world)
    s = cfg.sequence
    traj = drive(
        world,
        rig=s.rig,
        length_m=s.length_m,
        speed_mps=s.speed_mps,
        fps=s.fps,
        seed=s.seed,
        image_size=tuple(s.image_size),
    )
    step = np.linalg.norm(np.diff(traj.t_wc, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(step)])
    targets = np.arange(0.0, arc[-1] + 1e-9, s.keyframe_spacing_m)
    frames = np.unique(np.searchsorted(arc, targets))
    frames = frames[frames < len(traj)]
    lm = sample_landmarks(world, traj.t_wc[:, :2], cfg.landmarks, seed=cfg.seed)
    caster = SceneCaster.from_world(world)
    kf, pt, uv_true = visible_observations(
        caster, lm, traj.K, traj.R_wc[frames], traj.t_wc[frames], traj.image_size, cfg.landmarks
    )
    obs = simulate_observations(kf, pt, uv_true, traj.image_size, cfg.landmarks, seed=cfg.seed)
    C = frames.size
    data = SequenceData(
        K=traj.K,
        image_size=traj.image_size,
        timestamps=traj.timestamps[frames],
        R_wc_true=traj.R_wc[frames],
        t_wc_true=traj.t_wc[frames],
        observations=obs,
        num_points=len(lm),
        gps_xy=np.full((C, 2), np.nan),
    )
    logger.info(
        "sequence: %.0f m, %d keyframes, %d landmarks, %d observations (%.0f per keyframe, "
        "%d outliers)",
        arc[-1],
        C,
        len(lm),
        len(obs),
        len(obs) / max(C, 1),
        int(obs.is_outlier.sum()),
    )
    return Sequence(data, frames, traj, int(obs.is_outlier.sum()))


def gps_for_setting(cfg: ExperimentConfig, seq: Sequence, setting: str) -> np.ndarray:
    """GPS fixes of every keyframe for one setting.

    ``sigma=s``: the thesis's model for its synthetic sequence (§3.7.1.1): the true camera
    position plus ``N(0, s^2)`` per axis, no bias, no dropout. ``bias``: the locally constant bias
    + noise + dropouts of :func:`geoseg.synth.gps.simulate_gps` (``cfg.gps``), sampled at the
    frame rate so that every frame, hence every keyframe, has its fix (or a dropout).

    Returns:
        ``(C, 2)`` fixes, NaN for dropouts.
    """
    from geoseg.synth.gps import GpsConfig, simulate_gps

    traj = seq.trajectory
    if setting == "bias":
        gcfg = dataclasses.replace(cfg.gps, rate_hz=cfg.sequence.fps)
    elif setting.startswith("sigma="):
        sigma = float(setting.split("=", 1)[1])
        gcfg = GpsConfig(
            rate_hz=cfg.sequence.fps,
            bias_max_m=0.0,
            bias_std_m=0.0,
            noise_std_m=sigma,
            dropout_share=0.0,
        )
    else:
        raise SlamError(f"GPS setting: expected 'sigma=<m>' or 'bias', got {setting!r}")
    log = simulate_gps(traj.timestamps, traj.t_wc, gcfg, seed=cfg.seed + 17)
    idx = np.clip(
        np.round((traj.timestamps[seq.frames] - log.timestamps[0]) * gcfg.rate_hz), 0, len(log) - 1
    )
    return log.xy[idx.astype(np.int64)].copy()


def run_experiment(cfg: ExperimentConfig, out_dir: str | Path, *, force: bool = False) -> Path:
    """Run every (method, GPS setting) and write the tables, JSON and plots (a stage).

    Args:
        cfg: the experiment.
        out_dir: output directory (created).
        force: rerun even when ``out_dir`` holds results of the same config.

    Returns:
        ``out_dir``, holding ``fusion_ch3.md``, ``fusion_ch3.json``, ``trajectory.png``,
        ``memory.png``, ``config.json`` and ``runs/<method>_<setting>.npz`` (per-keyframe
        final and online poses, ground truth, GPS, Hessian bytes, fusion timings, fallbacks).
    """
    from geoseg.config import to_dict
    from slam_bridge import evaluate as ev

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg_json = json.dumps(to_dict(cfg), sort_keys=True, default=str)
    done = out / "fusion_ch3.json"
    if not force and done.is_file() and (out / "config.json").is_file():
        if (out / "config.json").read_text() == cfg_json:
            logger.info("%s already holds the results of this config; skipped", out)
            return out
    t0 = time.perf_counter()
    seq = make_sequence(cfg)
    (out / "runs").mkdir(exist_ok=True)
    runs: list[ev.RunSummary] = []
    results: dict[tuple[str, str], PipelineResult] = {}
    gps_of: dict[str, np.ndarray] = {}
    failures: list[dict] = []
    for setting in cfg.settings():
        gps_xy = gps_for_setting(cfg, seq, setting)
        gps_of[setting] = gps_xy
        data = dataclasses.replace(seq.data, gps_xy=gps_xy)
        for method in cfg.methods:
            try:
                res = run_pipeline(data, method, cfg.pipeline)
            except SlamError as exc:  # one failed run does not sink the grid: reported
                logger.error("%s / %s failed: %s", method, setting, exc)
                failures.append({"method": method, "setting": setting, "error": str(exc)})
                continue
            results[(method, setting)] = res
            np.savez_compressed(
                out / "runs" / f"{method}_{setting.replace('=', '')}.npz",
                R_wc=res.R_wc,
                t_wc=res.t_wc,
                R_wc_online=res.R_wc_online,
                t_wc_online=res.t_wc_online,
                t_wc_true=data.t_wc_true,
                R_wc_true=data.R_wc_true,
                gps_xy=gps_xy,
                hessian_bytes=np.array([r.hessian_bytes for r in res.records]),
                fusion_seconds_per_iteration=np.array(
                    [r.fusion_seconds_per_iteration for r in res.records]
                ),
                fusion_iterations=np.array([r.fusion_iterations for r in res.records]),
                fallback=np.array([r.fallback for r in res.records]),
            )
            runs.append(ev.summarize_run(res, data, setting))
            logger.info("%s / %s: %s", method, setting, runs[-1].short())
    if not runs:
        raise SlamError(f"every run failed: {failures}")
    summary = ev.build_summary(runs, cfg.methods, cfg.settings())
    summary["failures"] = failures
    summary["sequence_length_m"] = float(
        np.sum(np.linalg.norm(np.diff(seq.data.t_wc_true, axis=0), axis=1))
    )
    summary["keyframes"] = seq.data.num_keyframes
    summary["observations"] = len(seq.data.observations)
    summary["outliers_planted"] = seq.num_outliers
    summary["wall_seconds"] = time.perf_counter() - t0
    ev.write_json(summary, done)
    ev.write_markdown(summary, out / "fusion_ch3.md")
    first = cfg.settings()[-1]
    ev.plot_trajectories(
        out / "trajectory.png",
        seq.data.t_wc_true,
        {m: results[(m, first)].t_wc for m in cfg.methods if (m, first) in results},
        gps_of[first],
        title=f"trajectory vs GPS ({first}) vs ground truth",
    )
    ev.plot_memory(
        out / "memory.png",
        {
            m: np.array([r.hessian_bytes for r in results[(m, first)].records])
            for m in cfg.methods
            if (m, first) in results
        },
    )
    (out / "config.json").write_text(cfg_json)
    return out

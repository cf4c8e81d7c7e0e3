"""Tables and plots of the chapter-3 experiment (thesis §3.7, Tables 3.1-3.3, fig. 3.7).

* **Errors and inliers**: :mod:`slam_bridge.evaluation.metrics` (its docstring).
* **Time** per fusion iteration relative to ``n = 0`` (Table 3.3): the total fusion wall time
  over the total number of barrier iterations, divided by the same for ``n = 0``, over the
  keyframes whose window is full (``l`` free cameras: the regime the thesis's ratio describes;
  the start-up keyframes have small windows for every method). ``<method>_time_ratio_all``
  uses every keyframe.
* **Memory** (fig. 3.7): the Hessian memory of :func:`slam_bridge.slam.windows.hessian_bytes`; the
  ratio is the mean ``n = 0`` memory over the mean hybrid memory (keyframes where the hybrid's
  pose-graph window is full).
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from slam_bridge.evaluation.metrics import (
    count_inliers,
    error_stats,
    inlier_churn,
    inlier_loss,
    inlier_mask,
    rotation_errors,
    translation_errors,
)

logger = logging.getLogger(__name__)

__all__ = [
    "THESIS_TABLE_3_1",
    "THESIS_TABLE_3_2",
    "THESIS_TABLE_3_3",
    "loop_records",
    "RunSummary",
    "summarize_run",
    "build_summary",
    "write_json",
    "write_markdown",
    "plot_trajectories",
    "plot_memory",
]

#: Table 3.1 (synthetic 640 m sequence): (method, sigma_b) -> (mu_R, sigma_R, m_R, mu_T,
#: sigma_T, m_T, #inliers); "ba" = fusion BA/GPS (n = 0), "dpc"/"mpc" = hybrids (n = 30)
THESIS_TABLE_3_1: dict[tuple[str, float], tuple[float, ...]] = {
    ("ba", 0.0): (0.15, 0.01, 0.16, 0.15, 0.02, 0.16, 10427),
    ("ba", 0.75): (0.09, 0.04, 0.09, 0.68, 0.45, 0.80, 10422),
    ("ba", 1.5): (0.40, 0.24, 0.09, 0.45, 0.23, 0.40, 10462),
    ("dpc", 0.0): (0.09, 0.17, 0.04, 0.15, 0.02, 0.16, 10415),
    ("dpc", 0.75): (0.12, 0.18, 0.06, 0.63, 0.43, 0.54, 10282),
    ("dpc", 1.5): (0.42, 0.26, 0.41, 0.59, 0.9, 0.49, 10409),
    ("mpc", 0.0): (0.05, 0.04, 0.04, 0.15, 0.02, 0.16, 10369),
    ("mpc", 0.75): (0.29, 0.19, 0.27, 0.78, 0.50, 0.69, 10360),
    ("mpc", 1.5): (0.15, 0.19, 0.08, 1.26, 0.87, 1.02, 10439),
}
#: Table 3.2 (synthetic sequence): inlier loss (%) vs n = 0
THESIS_TABLE_3_2: dict[tuple[str, float], float] = {
    ("dpc", 0.0): 0.11,
    ("dpc", 0.75): 1.34,
    ("dpc", 1.5): 0.50,
    ("mpc", 0.0): 0.55,
    ("mpc", 0.75): 0.59,
    ("mpc", 1.5): 0.21,
}
#: Table 3.3 (simulations): time per iteration relative to n = 0
THESIS_TABLE_3_3: dict[str, float] = {"dpc": 0.40, "mpc": 0.66}
#: targets of the issue (the thesis's figures)
TARGETS = {"dpc_time_ratio": 0.40, "mpc_time_ratio": 0.66, "memory_ratio": 3.0, "inlier_loss": 0.01}
METHOD_LABEL = {"ba": "BA/GPS (n = 0)", "dpc": "hybrid DPC (n = 30)", "mpc": "hybrid MPC (n = 30)"}


@dataclass
class RunSummary:
    """The figures of one (method, GPS setting) run.

    Attributes:
        method: ``ba``, ``dpc`` or ``mpc``.
        setting: ``sigma=<m>`` or ``bias``.
        rotation: stats of the rotation errors (rad).
        translation: stats of the translation errors (m).
        horizontal: stats of the horizontal (x, y) translation errors (m): what the GPS sees.
        vertical: stats of ``|z_est - z_gt|`` (m): unobserved by the GPS (altitude ignored).
        inliers: inlier points, re-triangulated with the final poses (module docstring).
        inliers_raw: inlier points as stored by the SLAM.
        inliers_truth: inlier points re-triangulated with the true poses (module docstring).
        points: triangulated points.
        rejected_observations: observations deactivated as outliers.
        fusion_iterations: total barrier iterations.
        fusion_seconds: total barrier wall time.
        seconds_per_iteration: ``fusion_seconds / fusion_iterations``.
        fusion_seconds_full: fusion time over the full-window keyframes.
        fusion_iterations_full: barrier iterations over the full-window keyframes.
        hessian_bytes_mean: mean Hessian memory over the keyframes.
        hessian_bytes_full_mean: the same over keyframes with a full window (``l`` cameras).
        ba_seconds: total k-BA time.
        seconds: total wall time of the run.
        keyframes: keyframes processed.
        gps_fused: keyframes fused with a GPS fix.
        fallbacks: hybrid keyframes run as ``n = 0`` after failing the window consistency check
            (:attr:`slam_bridge.slam.windows.WindowConfig.consistency_share`); they count in the
            time and memory figures.
        inlier_points: ``(P,)`` bool, which points make ``inliers`` (for the churn against
            ``n = 0``; left out of the JSON), or None.
    """

    method: str
    setting: str
    rotation: dict
    translation: dict
    horizontal: dict
    vertical: dict
    inliers: int
    inliers_raw: int
    inliers_truth: int
    points: int
    rejected_observations: int
    fusion_iterations: int
    fusion_seconds: float
    seconds_per_iteration: float
    fusion_seconds_full: float
    fusion_iterations_full: int
    hessian_bytes_mean: float
    hessian_bytes_full_mean: float
    ba_seconds: float
    seconds: float
    keyframes: int
    gps_fused: int
    fallbacks: int = 0
    inlier_points: np.ndarray | None = field(default=None, repr=False)

    def short(self) -> str:
        """One line for logs."""
        return (
            f"T {self.translation['mean']:.3f}+-{self.translation['std']:.3f} m "
            f"(xy {self.horizontal['mean']:.3f}, z {self.vertical['mean']:.3f}), "
            f"R {self.rotation['mean']:.4f} rad, inliers {self.inliers} ({self.inliers_raw} raw), "
            f"{1e3 * self.seconds_per_iteration:.1f} ms/it, {self.seconds:.0f} s"
        )


def loop_records(result) -> list:
    """The records of the keyframes the loop tracked and optimised (not the start-up's)."""
    return [r for r in result.records if r.tracking in ("tracked", "weak")]


def summarize_run(
    result, R_wc_true: np.ndarray, t_wc_true: np.ndarray, setting: str, *, skip: int = 0
) -> RunSummary:
    """Evaluate a :class:`slam_bridge.slam.loop.SlamResult` against the true poses.

    Args:
        result: the run.
        R_wc_true: ``(C', 3, 3)`` true keyframe rotations (``C' >= C``, the run's keyframes).
        t_wc_true: ``(C', 3)`` true optical centres.
        setting: GPS setting name.
        skip: leading keyframes left out of the error statistics (the start poses are exact).

    Returns:
        A :class:`RunSummary`.
    """
    m = result.map
    C = m.num_keyframes
    sl = slice(skip, C)
    e_T = translation_errors(m.t_wc[sl], t_wc_true[:C][sl])
    e_R = rotation_errors(m.R_wc[sl], R_wc_true[:C][sl])
    args = (m.K, m.R_wc, m.t_wc, m.X_w, m.obs_keyframe, m.obs_point, m.obs_uv)
    kw = dict(used=m.obs_active, triangulated=m.triangulated)
    in_mask = inlier_mask(*args, retriangulate=True, **kw)
    n_raw = count_inliers(*args, **kw)
    truth = (R_wc_true[:C], t_wc_true[:C])
    n_truth = count_inliers(m.K, *truth, *args[3:], retriangulate=True, **kw)
    recs = loop_records(result)
    it = sum(r.fusion_iterations for r in recs)
    fs = sum(r.fusion_seconds_per_iteration * r.fusion_iterations for r in recs)
    mem = np.array([r.hessian_bytes for r in recs], dtype=float)
    full = np.array([r.n_cameras for r in recs])
    full_mask = full >= (full.max() if full.size else 0)
    return RunSummary(
        method=result.method,
        setting=setting,
        rotation=error_stats(e_R),
        translation=error_stats(e_T),
        horizontal=error_stats(np.linalg.norm(m.t_wc[sl, :2] - t_wc_true[:C][sl, :2], axis=1)),
        vertical=error_stats(np.abs(m.t_wc[sl, 2] - t_wc_true[:C][sl, 2])),
        inliers=int(in_mask.sum()),
        inliers_raw=n_raw,
        inliers_truth=n_truth,
        points=int(m.triangulated.sum()),
        rejected_observations=int((~m.obs_active).sum()),
        fusion_iterations=int(it),
        fusion_seconds=float(fs),
        seconds_per_iteration=float(fs / it) if it else float("nan"),
        fusion_seconds_full=float(
            sum(
                r.fusion_seconds_per_iteration * r.fusion_iterations
                for r, f in zip(recs, full_mask)
                if f
            )
        ),
        fusion_iterations_full=int(sum(r.fusion_iterations for r, f in zip(recs, full_mask) if f)),
        hessian_bytes_mean=float(mem.mean()) if mem.size else 0.0,
        hessian_bytes_full_mean=float(mem[full_mask].mean()) if mem.size else 0.0,
        ba_seconds=float(sum(r.ba_seconds for r in recs)),
        seconds=float(result.seconds),
        keyframes=int(C),
        gps_fused=int(sum(r.gps_used for r in recs)),
        fallbacks=int(sum(r.fallback for r in recs)),
        inlier_points=in_mask,
    )


def _sigma_of(setting: str) -> float | None:
    return float(setting.split("=", 1)[1]) if setting.startswith("sigma=") else None


def build_summary(runs: list[RunSummary], methods: list[str], settings: list[str]) -> dict:
    """The flat results object (``bench/results/fusion_ch3.json``) plus ``runs`` (nested).

    Flat keys: ``<method>_<setting>_{t_mean,t_std,t_median,r_mean,r_std,r_median,inliers}``,
    ``<method>_time_ratio`` / ``<method>_memory_ratio`` / ``<method>_inlier_loss_max`` for the
    hybrids, and ``dpc_time_ratio``, ``mpc_time_ratio``, ``memory_ratio`` (n = 0 memory over the
    larger hybrid memory: the worse of the two), ``inlier_loss_max`` (worst over hybrids and
    settings).
    """
    by = {(r.method, r.setting): r for r in runs}
    out: dict = {}
    for r in runs:
        key = f"{r.method}_{r.setting.replace('sigma=', 'sigma')}"
        out[f"{key}_t_mean"] = r.translation["mean"]
        out[f"{key}_t_std"] = r.translation["std"]
        out[f"{key}_t_median"] = r.translation["median"]
        out[f"{key}_r_mean"] = r.rotation["mean"]
        out[f"{key}_r_std"] = r.rotation["std"]
        out[f"{key}_r_median"] = r.rotation["median"]
        out[f"{key}_th_mean"] = r.horizontal["mean"]
        out[f"{key}_tz_mean"] = r.vertical["mean"]
        out[f"{key}_inliers"] = r.inliers
        out[f"{key}_inliers_raw"] = r.inliers_raw
        if r.method != "ba":
            out[f"{key}_fallbacks"] = r.fallbacks
        out[f"{key}_inliers_truth"] = r.inliers_truth
    losses, mem_ratios = [], []
    if "ba" in methods:
        for m in (x for x in methods if x != "ba"):
            both = [s for s in settings if ("ba", s) in by and (m, s) in by]
            if not both:
                continue
            settings_m, settings = settings, both
            for suffix, tk, ik in (
                ("", "fusion_seconds_full", "fusion_iterations_full"),
                ("_all", "fusion_seconds", "fusion_iterations"),
            ):
                t_ba = sum(getattr(by[("ba", s)], tk) for s in settings)
                i_ba = sum(getattr(by[("ba", s)], ik) for s in settings)
                t_m = sum(getattr(by[(m, s)], tk) for s in settings)
                i_m = sum(getattr(by[(m, s)], ik) for s in settings)
                if i_ba and i_m and t_ba > 0:
                    out[f"{m}_time_ratio{suffix}"] = (t_m / i_m) / (t_ba / i_ba)
            mem_ba = np.mean([by[("ba", s)].hessian_bytes_full_mean for s in settings])
            mem_m = np.mean([by[(m, s)].hessian_bytes_full_mean for s in settings])
            out[f"{m}_memory_ratio"] = float(mem_ba / mem_m)
            mem_ratios.append(out[f"{m}_memory_ratio"])
            ls = []
            for s in settings:
                loss = inlier_loss(by[(m, s)].inliers, by[("ba", s)].inliers)
                key = f"{m}_{s.replace('sigma=', 'sigma')}"
                out[f"{key}_inlier_loss"] = loss
                ls.append(loss)
                churn = inlier_churn(by[("ba", s)].inlier_points, by[(m, s)].inlier_points)
                if churn is not None:
                    lost, gained = churn
                    out[f"{key}_inliers_lost"], out[f"{key}_inliers_gained"] = lost, gained
                    out[f"{key}_inlier_loss_noise"] = float(
                        np.sqrt(lost + gained) / by[("ba", s)].inliers
                    )
            out[f"{m}_inlier_loss_max"] = max(ls)
            out[f"{m}_inlier_loss_raw_max"] = max(
                inlier_loss(by[(m, s)].inliers_raw, by[("ba", s)].inliers_raw) for s in settings
            )
            losses.extend(ls)
            settings = settings_m
    if mem_ratios:
        out["memory_ratio"] = float(min(mem_ratios))
    if losses:
        out["inlier_loss_max"] = float(max(losses))
    out["methods"] = list(methods)
    out["settings"] = list(settings)
    out["runs"] = [{k: v for k, v in asdict(r).items() if k != "inlier_points"} for r in runs]
    return out


def write_json(summary: dict, path: str | Path) -> Path:
    """Write ``summary`` as indented JSON (NaN written as null)."""
    path = Path(path)

    def clean(v):
        if isinstance(v, float) and not np.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list):
            return [clean(x) for x in v]
        if isinstance(v, np.generic):
            return clean(v.item())
        return v

    path.write_text(json.dumps(clean(summary), indent=2, sort_keys=False) + "\n")
    return path


def _f(x, nd: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{nd}f}"


def markdown_tables(summary: dict) -> str:
    """Tables 3.1-3.3 and the memory ratio as Markdown, the thesis's figures beside ours."""
    runs = summary["runs"]
    lines = [
        "### Table 3.1: errors against ground truth (rotation rad, translation m)",
        "",
        "| method | GPS | mu_R | sigma_R | m_R | mu_T | sigma_T | m_T | mu_T xy | mu_T z | #inliers "
        "| #inliers at true poses | thesis mu_R / mu_T / m_T | mu_T no worse than thesis |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        sig = _sigma_of(r["setting"])
        th = THESIS_TABLE_3_1.get((r["method"], sig)) if sig is not None else None
        ref = f"{th[0]:.2f} / {th[3]:.2f} / {th[5]:.2f}" if th else "-"
        ok = ("yes" if r["translation"]["mean"] <= th[3] else "no") if th else "-"
        lines.append(
            f"| {METHOD_LABEL[r['method']]} | {r['setting']} | {_f(r['rotation']['mean'], 3)} | "
            f"{_f(r['rotation']['std'], 3)} | {_f(r['rotation']['median'], 3)} | "
            f"{_f(r['translation']['mean'])} | {_f(r['translation']['std'])} | "
            f"{_f(r['translation']['median'])} | {_f(r['horizontal']['mean'])} | "
            f"{_f(r['vertical']['mean'])} | {r['inliers']} | {r.get('inliers_truth', '-')} | "
            f"{ref} | {ok} |"
        )
    lines += [
        "",
        "### Table 3.2: inlier loss vs n = 0 (%) (re-triangulated with the final poses; stored)",
        "",
        "Chance sd: sqrt(lost + gained) / N_0, the spread of the net loss if those points had "
        "flipped either way by chance (module docstring).",
        "",
        "| method | GPS | ours | ours (stored points) | points lost / gained | chance sd | thesis |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in summary["methods"]:
        if m == "ba":
            continue
        for s in summary["settings"]:
            key = f"{m}_{s.replace('sigma=', 'sigma')}"
            v = summary.get(f"{key}_inlier_loss")
            noise = summary.get(f"{key}_inlier_loss_noise")
            churn = (
                f"{summary[f'{key}_inliers_lost']} / {summary[f'{key}_inliers_gained']}"
                if f"{key}_inliers_lost" in summary
                else "-"
            )
            rr = {(r["method"], r["setting"]): r["inliers_raw"] for r in runs}
            raw = (
                inlier_loss(rr[(m, s)], rr[("ba", s)]) if ("ba", s) in rr and (m, s) in rr else None
            )
            th = THESIS_TABLE_3_2.get((m, _sigma_of(s))) if _sigma_of(s) is not None else None
            lines.append(
                f"| {METHOD_LABEL[m]} | {s} | {_f(None if v is None else 100 * v)} | "
                f"{_f(None if raw is None else 100 * raw)} | {churn} | "
                f"{_f(None if noise is None else 100 * noise)} | {_f(th)} |"
            )
    lines += [
        "",
        "### Table 3.3 and fig. 3.7: time per fusion iteration and Hessian memory vs n = 0",
        "",
        "| method | time ratio (ours) | thesis | target | memory n=0 / hybrid | target |",
        "|---|---|---|---|---|---|",
    ]
    for m in summary["methods"]:
        if m == "ba":
            continue
        lines.append(
            f"| {METHOD_LABEL[m]} | {_f(summary.get(f'{m}_time_ratio'))} | "
            f"{_f(THESIS_TABLE_3_3.get(m))} | <= {_f(TARGETS[f'{m}_time_ratio'])} | "
            f"{_f(summary.get(f'{m}_memory_ratio'))} | >= 3 |"
        )
    falls = {
        m: [(r["setting"], r["fallbacks"]) for r in runs if r["method"] == m and r.get("fallbacks")]
        for m in summary["methods"]
        if m != "ba"
    }
    if any(falls.values()):
        lines += [
            "",
            "Keyframes run as n = 0 after failing the window consistency check (counted in the "
            "time and memory ratios): "
            + "; ".join(
                f"{METHOD_LABEL[m]}: " + ", ".join(f"{s} {c}" for s, c in v)
                for m, v in falls.items()
                if v
            )
            + ".",
        ]
    for fail in summary.get("failures", []):
        lines.append(f"\nFAILED: {fail['method']} / {fail['setting']}: {fail['error']}")
    ba_runs = [r for r in runs if r["method"] == "ba"]
    if ba_runs:
        ms = np.mean([r["seconds_per_iteration"] for r in ba_runs]) * 1e3
        lines += ["", f"n = 0: {ms:.1f} ms per fusion iteration (thesis: ~300 ms at 1.6 GHz)."]
    return "\n".join(lines) + "\n"


def write_markdown(summary: dict, path: str | Path) -> Path:
    """Write :func:`markdown_tables` to ``path``."""
    path = Path(path)
    path.write_text(markdown_tables(summary))
    return path


def plot_trajectories(
    path: str | Path,
    t_true: np.ndarray,
    estimates: dict[str, np.ndarray],
    gps_xy: np.ndarray | None = None,
    *,
    title: str = "",
) -> Path:
    """Top view: ground truth, GPS fixes and the estimated trajectories (PNG).

    Args:
        path: output file.
        t_true: ``(C, 3)`` true optical centres.
        estimates: ``{name: (C', 3)}`` estimated centres.
        gps_xy: ``(C, 2)`` GPS fixes (NaN = dropout) or None.
        title: figure title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    ax.plot(t_true[:, 0], t_true[:, 1], "k-", lw=2, label="ground truth")
    if gps_xy is not None:
        ax.plot(gps_xy[:, 0], gps_xy[:, 1], "x", color="0.5", ms=3, label="GPS")
    for name, t in estimates.items():
        ax.plot(t[:, 0], t[:, 1], "-", lw=1, label=METHOD_LABEL.get(name, name))
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)


def plot_memory(path: str | Path, memory: dict[str, np.ndarray]) -> Path:
    """Hessian memory per keyframe for each method (fig. 3.7 analogue, PNG, kB)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    colors = {"ba": "red", "dpc": "green", "mpc": "blue"}
    for name, mem in memory.items():
        ax.plot(
            np.asarray(mem) / 1024.0, color=colors.get(name), label=METHOD_LABEL.get(name, name)
        )
    ax.set_xlabel("keyframe")
    ax.set_ylabel("Hessian memory (kB)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)

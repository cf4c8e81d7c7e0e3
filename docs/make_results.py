"""Write docs/results.md, the README's results table and its demo figures from bench/results/.

Usage, from anywhere::

    python docs/make_results.py            # rewrite docs/results.md and the README block
    python docs/make_results.py --check    # exit 1 when either is out of date

Every ``bench/<name>.py`` writes ``bench/results/<name>.json``: one flat object, figure name ->
value, plus its provenance (``command``, ``git_commit``, ``machine``, ``date``, ``split``:
``bench/provenance.py``), listed first in the file's section. This script never holds a number itself: the headline
table picks figures by key (:data:`HEADLINE`, with the target and the thesis's figure beside
each), and one section per results file lists all of its figures. A results file the script does
not know (a new benchmark) still gets its section; a headline figure whose file or key is
missing is left out. To add a headline line, append to :data:`HEADLINE`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
PAGE = ROOT / "docs" / "results.md"
README = ROOT / "README.md"
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
#: the keys that say where a results file's figures come from (``bench/provenance.py``)
PROVENANCE = ("command", "git_commit", "date", "split", "machine")


def _num(v: float) -> str:
    if abs(v) >= 1000:
        return f"{v:,.0f}"
    return f"{v:.3g}" if v == round(v) else f"{v:#.3g}"  # 0.630, not 0.63; 0 stays 0


def _pct(v: float) -> str:
    return f"{100 * v:.1f} %"


@dataclass(frozen=True)
class Figure:
    """One headline line: ``keys`` of ``bench/results/<file>.json`` shown ``" / "``-joined."""

    file: str
    keys: tuple[str, ...]
    label: str
    target: str
    thesis: str = "-"
    unit: str = ""
    fmt: Callable[[float], str] = _num


HEADLINE: tuple[Figure, ...] = (
    Figure(
        "accuracy_seg",
        ("miou", "miou_std"),
        "segmentation mIoU, five held-out cities: mean / std",
        ">= 0.80 (mean)",
        fmt=lambda v: f"{v:.3f}",  # the std to the mean's decimals
    ),
    Figure(
        "accuracy_seg",
        ("building_iou", "building_iou_std"),
        "building IoU, five held-out cities: mean / std",
        ">= 0.90 (mean)",
        fmt=lambda v: f"{v:.3f}",
    ),
    Figure(
        "accuracy_seg",
        ("normals_building_median_deg", "normals_building_median_deg_std"),
        "normal error on building pixels, median, five held-out cities: mean / std",
        "<= 10 (mean)",
        unit=" deg",
        fmt=lambda v: f"{v:.2f}",
    ),
    Figure(
        "accuracy_seg",
        (
            "dirichlet_fp_removed",
            "dirichlet_fp_removed_std",
            "dirichlet_extra_false_rejections",
            "dirichlet_extra_false_rejections_std",
        ),
        "Dirichlet filter, five held-out cities: building false positives removed (mean / std) "
        "/ extra false rejections (mean / std)",
        ">= 70 % / - / <= 15 % / -",
        "~70 % / ~15 %",
        fmt=_pct,
    ),
    Figure(
        "accuracy_reloc",
        ("recall_at_1_raw_layer21", "recall_at_1", "recall_at_1_reranked"),
        "place recognition Recall@1, whole base: raw layer-21 / learned / re-ranked (mean of "
        "five held-out cities)",
        ">= 0.928",
        "0.928 (raw layer-21)",
    ),
    Figure(
        "accuracy_reloc",
        ("recall_at_1_raw_layer21_std", "recall_at_1_std", "recall_at_1_reranked_std"),
        "the same: std over the five cities",
        "-",
    ),
    Figure(
        "accuracy_reloc",
        ("recall_at_1_gps_window_reranked_gps", "recall_at_1_gps_window_reranked_gps_std"),
        "place recognition Recall@1 in the GPS window (re-ranked, GPS-fused): mean / std over "
        "five cities",
        ">= 0.996",
        "0.996 (raw layer-21)",
    ),
    Figure(
        "accuracy_reloc",
        ("recall_at_1_sequence", "recall_at_1_sequence_std"),
        "place recognition Recall@1, queries as one drive (route filter): mean / std",
        "reported",
    ),
    Figure(
        "accuracy_reloc",
        ("triplet_accuracy", "triplet_accuracy_std"),
        "triplet accuracy: mean / std",
        ">= 0.94",
        "0.94",
    ),
    Figure(
        "accuracy_reloc",
        ("relpose_rot_median_deg", "relpose_rot_median_deg_std", "relpose_dir_median_deg"),
        "relative pose, median error: rotation (mean / std) / direction (mean)",
        "<= 2 / - / <= 10",
        unit=" deg",
    ),
    Figure(
        "accuracy_reloc",
        ("abs_position_median_m", "abs_position_median_m_std", "abs_position_p90_m"),
        "query position, 0.5-10 m from the base images: median (mean / std) / p90 (mean)",
        "<= 2 (median)",
        unit=" m",
    ),
    Figure(
        "accuracy_reloc",
        (
            "position_error_at_base_poses_m",
            "position_error_at_base_poses_m_std",
            "position_error_at_base_poses_p90_m",
        ),
        "query position, taken at a base pose: median (mean / std) / p90 (mean)",
        "<= 0.5 (median)",
        unit=" m",
    ),
    Figure(
        "inference_speed",
        ("normals_head_overhead_pct",),
        "normals head's extra parameters over ENet",
        "~10-15",
        "~10",
        unit=" %",
    ),
    Figure(
        "inference_speed",
        ("ort_over_lraspp_640x480",),
        "joint network CPU time / LRASPP's, 640x480",
        "<= 0.8",
    ),
    Figure(
        "inference_speed",
        ("gpu_batch1_ms_640x480",),
        "joint network latency on an H100, 640x480",
        "<= 2",
        "76 (GTX 860M)",
        unit=" ms",
    ),
    Figure(
        "render_speed",
        ("fps_320x240", "fps_640x480"),
        "synthetic world rendering, frames/s at 320x240 / 640x480",
        ">= 25 / >= 5",
    ),
    Figure("ba_speed", ("iter_time_over_ceres_c40",), "k-BA time per iteration / Ceres's", "<= 1"),
    Figure(
        "fusion_ch3",
        ("dpc_time_ratio", "mpc_time_ratio"),
        "fusion time per iteration vs n = 0: DPC / MPC",
        "<= 0.40 / <= 0.66",
        "0.40-0.45 / 0.66-0.72",
    ),
    Figure("fusion_ch3", ("memory_ratio",), "Hessian memory, n = 0 / hybrid", ">= 3", "~3"),
    Figure(
        "fusion_ch3",
        ("inlier_loss_max",),
        "worst inlier loss of the hybrids vs n = 0",
        "<= 1 %",
        "0.1-1.3 %",
        fmt=_pct,
    ),
    Figure(
        "fusion_ch3",
        ("ba_sigma0.75_t_mean", "dpc_sigma0.75_t_mean", "mpc_sigma0.75_t_mean"),
        "translation error, GPS sigma_b 0.75 m: n = 0 / DPC / MPC",
        "thesis's",
        "0.68 / 0.63 / 0.78",
        unit=" m",
    ),
    Figure(
        "slam_images",
        ("translation_error_m", "gps_error_m"),
        "SLAM on images: horizontal error / the raw GPS fixes'",
        "SLAM <= 0.5 x GPS",
        unit=" m",
    ),
    Figure(
        "slam_images",
        ("bad_observation_share", "tracking_failures"),
        "SLAM on images: share of observations > 2 px off / lost keyframes",
        "<= 0.02 / 0",
    ),
    Figure(
        "slam_images",
        ("rotation_error_deg",),
        "SLAM on images: rotation error",
        "<= 0.5",
        unit=" deg",
    ),
    Figure(
        "slam_images", ("frames_per_second",), "SLAM on images: frames per second (CPU)", ">= 10"
    ),
    Figure(
        "slam_images_report",
        ("translation_error_over_gps", "translation_error_over_gps_std", "rotation_error_deg"),
        "SLAM on images, five drives no setting was chosen on: error / the fixes' (mean, std); "
        "rotation error",
        "<= 0.5 / - / <= 0.5 deg",
    ),
    Figure(
        "slam_real",
        ("real_translation_error_over_gps_mean", "real_translation_error_over_gps_max"),
        "SLAM on real KITTI clips (GPS simulated): error / the fixes', mean / max",
        "<= 0.6 / <= 1.0",
    ),
    Figure(
        "slam_real",
        ("real_translation_error_over_oracle_mean", "real_scale_error_max"),
        "SLAM on real clips: error / the true shape fitted to the fixes; odometry-only scale error",
        "<= 1.25 / <= 0.03",
    ),
    Figure(
        "slam_real",
        ("real_rotation_error_deg_mean", "real_rotation_error_deg_max"),
        "SLAM on real clips: rotation error, mean / max",
        "<= 1.0 / <= 2.0",
        unit=" deg",
    ),
    Figure(
        "slam_real",
        (
            "real_heading_error_deg_mean",
            "real_oracle_heading_error_deg_mean",
            "real_tilt_error_deg_mean",
        ),
        "SLAM on real clips: heading error / the oracle's / tilt error (which 2-D fixes do not "
        "measure), mean",
        "-",
        unit=" deg",
    ),
    Figure(
        "slam_real",
        ("real_tracking_failures", "real_status_failed", "real_frames_per_second"),
        "SLAM on real clips: lost keyframes / failed runs / frames per second (1226x370)",
        "0 / 0 / >= 10 (idle)",
    ),
    Figure(
        "reloc_real",
        (
            "real_reloc_position_error_m_mean",
            "real_reloc_best_match_error_m_mean",
            "real_reloc_gated_share",
        ),
        "relocalising real KITTI frames (base: every other frame): position error / the best "
        "match's / share where the heads' rays disagreed",
        "<= best match's",
        fmt=_num,
    ),
    Figure(
        "accuracy_real_street",
        ("real_labels_miou", "real_labels_building_iou", "grayscale_miou_ratio"),
        "real images (CamVid val, native), `street` (real labels, user-installed): mIoU / "
        "building IoU / grey-image mIoU ratio",
        ">= 0.75 / >= 0.85 / >= 0.95",
    ),
    Figure(
        "accuracy_real",
        ("zero_shot_miou", "zero_shot_building_iou"),
        "real images (CamVid val, 7 classes), `seg` (plain synthetic city): mIoU / building IoU",
        "- (`seg_real`'s, below)",
    ),
    Figure(
        "accuracy_real_seg_real",
        ("zero_shot_miou", "zero_shot_building_iou"),
        "real images (CamVid val), `seg_real` (randomised synthetic city only): mIoU / building IoU",
        ">= 0.55 / >= 0.70",
    ),
    Figure(
        "accuracy_real_seg_real",
        ("heldout_synthetic_miou_48_frames", "heldout_synthetic_miou_96_frames"),
        "`seg_real` on the held-out synthetic city at 480x360: mIoU on 48 / 96 frames",
        ">= 0.80",
    ),
    Figure(
        "accuracy_real_naive_real",
        ("zero_shot_miou", "zero_shot_building_iou", "dirichlet_fp_removed"),
        "real images (CamVid val), `naive_real` (2015 patch CNN, randomised city): mIoU / "
        "building IoU / building false positives its Dirichlet filter removes",
        "-",
    ),
    Figure(
        "accuracy_real_naive_real",
        ("heldout_dirichlet_fp_removed", "heldout_dirichlet_extra_false_rejections"),
        "`naive_real` on the held-out synthetic city, with `dirichlet_real_synth` (its filter "
        "for renders): building false positives removed / extra false rejections",
        ">= 70 % / <= 15 %",
        "~70 % / ~15 %",
        fmt=_pct,
    ),
    Figure(
        "accuracy_real",
        ("finetuned_miou", "scratch_miou"),
        "real images, fine-tuned on CamVid train: from the shipped weights / from scratch",
        ">= 0.72 (shipped)",
    ),
    Figure(
        "buildings_ch4",
        ("association_precision_bayes", "association_precision_raycast"),
        "building association precision: network + eq. 4.14 / ray-cast baseline",
        ">= 0.95 (network)",
        "baseline takes trees for facades",
    ),
    Figure(
        "buildings_ch4",
        (
            "translation_error_m_nobuild_exact",
            "translation_error_m_raycast_exact",
            "translation_error_m_bayes_exact",
            "translation_error_m_oracle_exact",
        ),
        "1.2 km tuning drive, exact building model, no GPS: error without buildings / baseline / "
        "network / oracle",
        "<= 0.05 (network)",
        "0.013 (2015: naive CNN + Dirichlet)",
        unit=" m",
    ),
    Figure(
        "buildings_ch4",
        (
            "translation_error_m_nobuild_gis",
            "translation_error_m_raycast_gis",
            "translation_error_m_bayes_gis",
        ),
        "1.2 km tuning drive, GIS model with errors, GPS 0.75 m: without buildings / baseline / "
        "network",
        "network <= without",
        unit=" m",
    ),
    Figure(
        "buildings_ch4_report",
        (
            "translation_error_m_nobuild_exact_mean",
            "translation_error_m_raycast_exact_mean",
            "translation_error_m_bayes_exact_mean",
            "translation_error_m_oracle_exact_mean",
        ),
        "five 300 m report drives, exact model, no GPS: mean error without buildings / baseline "
        "/ network / oracle",
        "<= 0.05 (network)",
        unit=" m",
    ),
    Figure(
        "buildings_ch4_report",
        ("translation_error_m_bayes_exact_std", "translation_error_m_bayes_exact_async_mean"),
        "the same, network: spread over the drives (std) / mean as users run it (asynchronous "
        "worker, every keyframe)",
        "<= 0.05 (as run)",
        unit=" m",
    ),
    Figure(
        "buildings_ch4_report",
        ("association_precision_bayes_mean", "association_precision_raycast_mean"),
        "five report drives: association precision, network / baseline (mean)",
        ">= 0.95 (network)",
    ),
    Figure(
        "buildings_ch4_report",
        (
            "translation_error_m_nobuild_gis_mean",
            "translation_error_m_raycast_gis_mean",
            "translation_error_m_bayes_gis_mean",
        ),
        "five report drives, GIS model, GPS 0.75 m: without buildings / baseline / network (mean)",
        "network <= without",
        unit=" m",
    ),
    Figure(
        "colour_transfer_ch4",
        (
            "shifted_translation_error_m_bayes_exact_plain_mean",
            "shifted_translation_error_m_bayes_exact_transfer_mean",
            "control_translation_error_m_bayes_exact_plain_mean",
            "control_translation_error_m_bayes_exact_transfer_mean",
        ),
        "chapter 4 through another camera's colours (warm cast, darker mid-tones), exact model, "
        "no GPS: network as given / with the colour transfer (card); the same on the render",
        "with < as given (cast); with ~ as given (render)",
        unit=" m",
    ),
    Figure(
        "colour_transfer_ch4",
        (
            "shifted_association_precision_bayes_exact_plain_mean",
            "shifted_association_precision_bayes_exact_transfer_mean",
            "shifted_association_recall_bayes_exact_plain_mean",
            "shifted_association_recall_bayes_exact_transfer_mean",
        ),
        "the same, cast drives: association precision as given / with; recall as given / with",
        "with >= as given",
    ),
    Figure(
        "buildings_ch4_occluded",
        (
            "occluded_translation_error_m_raycast_exact",
            "occluded_translation_error_m_bayes_exact",
            "chapter4_translation_error_m_raycast_exact",
        ),
        "occluders within 1-2 m of the facades (fig. 4.13), exact model, five 250 m report "
        "drives: baseline / network (mean); the baseline in the chapter-4 city, same seeds",
        "-",
        "baseline drifts, loses tracking after ~50 keyframes",
        unit=" m",
    ),
    Figure(
        "buildings_ch4_occluded",
        ("occluded_tracking_failures_raycast_exact",),
        "the same: the baseline's tracking failures (mean per drive)",
        "-",
        "lost after ~50 keyframes",
    ),
    Figure(
        "reloc_slam",
        ("noGPS_base_translation_error_m", "base_fix_error_m"),
        "SLAM from an image base (winter traversal), no GPS: mean error / the base's fixes' error",
        "<= 0.5",
        unit=" m",
    ),
    Figure(
        "reloc_slam",
        ("gps_plus_base_translation_error_m", "gps_only_translation_error_m"),
        "SLAM with GPS 0.75 m: with the image base / GPS only",
        "with <= without",
        unit=" m",
    ),
    Figure(
        "refine",
        ("pseudo_truth_error_m", "run_translation_error_m"),
        "pseudo ground truth (global k-BA constrained to buildings + DEM, GPS 0.75 m), three "
        "report drives: refined / the run (mean horizontal keyframe error)",
        "refined <= run",
        unit=" m",
    ),
    Figure(
        "refine",
        ("biased_gps_pseudo_truth_error_m", "biased_gps_run_translation_error_m"),
        "the same with the biased GPS (up to 3 m): refined / the run",
        "refined <= run",
        unit=" m",
    ),
    Figure(
        "buildings_ch4",
        ("async_time_ratio",),
        "SLAM loop time per keyframe with the network worker on / off",
        "<= 1.1",
    ),
    Figure(
        "buildings_ch4_timing",
        ("async_time_ratio", "building_rows_time_ratio", "async_time_ratio_same_rows"),
        "the same on a second host: worker on / off; of which the building rows' fusion / the "
        "worker beside the same rows",
        "<= 1.1",
    ),
)

# One line on what each known benchmark measures (unknown files get their script's first line).
ABOUT: dict[str, str] = {
    "demo": "What `geoseg demo` prints, from a run of the demo with its defaults "
    "(`bench/demo.py`); the README's demo paragraph is written from it.",
    "accuracy_seg": "ENet labels, the joint normals, the naive CNN and its Dirichlet filter on "
    "one render of each of five held-out synthetic cities (`bench/splits.py`'s "
    "`SEG_REPORT_CITIES`, all conditions, `sun_low` never trained on): each figure the mean over "
    "the renders, `_std` their standard deviation, counts summed, every render's figures under "
    "`per_render`.",
    "accuracy_reloc": "Relocalisation on five held-out cities (`RELOC_REPORT_CITIES` of "
    "`bench/splits.py`: no network trained and no setting chosen there), one render each: a "
    "summer tram drive of 1.5 km is the image base, a winter drive 3 m further along the track "
    "the queries (thesis §5.1); the `position_error_at_base_poses` figures use winter queries "
    "taken exactly at the base poses (`geoseg.reloc.localizer.Localizer`, GPS window; "
    "`_sequence`: the route filter, no GPS). Each figure is the mean over the cities, `_std` its "
    "sample std, `per_render.<figure>` its value in each city (in the order of `renders`). The "
    "relative poses are the shipped head's, its distance gated with the near head "
    "(`relpose_near`, `geoseg.reloc.networks.GatedRelPoseHead`).",
    "inference_speed": "Network sizes, CPU time (onnxruntime vs the LRASPP baseline, side by "
    "side in one run), int8 quantisation, and GPU latency (`gpu_*`, on a lent H100).",
    "render_speed": "Frames per second of the synthetic world's ray-casting renderer.",
    "ba_speed": "Keyframe bundle adjustment time per iteration against Ceres and GTSAM on the "
    "same problems.",
    "fusion_ch3": "The chapter-3 experiment: n = 0 against the hybrid DPC and MPC windows with "
    "GPS fusion (Tables 3.1-3.3, fig. 3.7); full tables in `bench/results/fusion_ch3_full/`.",
    "accuracy_real": "The networks on real street photographs: CamVid val (101 frames, the 7 "
    "classes CamVid labels), the synthetic-only shipped weights zero-shot (with and without "
    "colour transfer) and fine-tuned on CamVid train for a fixed budget, beside the same budget "
    "from scratch; see docs/real_images.md.",
    "accuracy_real_seg_real": "The shipped `seg_real` weights (`configs/seg_real.yaml` then "
    "`configs/seg_real_480.yaml`: the shipped `seg` fine-tuned on the randomised synthetic city "
    "at 320x240, then at 480x360, averaged 0.8 : 0.2 with the same stage two on cities with "
    "parked cars, `configs/seg_real_parked.yaml`, and that average 0.9 : 0.1 with `seg`; no real "
    "image) on CamVid val, "
    "zero-shot, with and without colour transfer, and what CamVid's labels say of the normals "
    "of `normals_real` (its joint network); see docs/real_images.md.",
    "buildings_ch4": "Building constraints chosen by the networks (thesis chapter 4): a 1.2 km "
    "drive with loops through a city full of trees, vehicles and shelters, the image SLAM with "
    "the ray-cast baseline, the naive CNN + Dirichlet filter, the joint network + eq. 4.14 and "
    "an oracle, against the exact building model (odometry + elevation, no GPS, a 60-keyframe "
    "window) and the GIS model with its errors (GPS sigma_b 0.75 m); see docs/bridge.md.",
    "accuracy_real_naive": "The shipped 2015 naive patch CNN (synthetic only) zero-shot on "
    "CamVid val, and what CamVid's labels say of the shipped joint network's normals; see "
    "docs/real_images.md.",
    "accuracy_real_naive_real": "The shipped `naive_real` patch CNN (`configs/naive_real.yaml`: "
    "`naive` fine-tuned on the randomised synthetic city) zero-shot on CamVid val, and its "
    "Dirichlet filter `dirichlet_real` on its building predictions; see docs/real_images.md.",
    "buildings_ch4_timing": "The chapter-4 experiment's timing pairs with the asynchronous run's "
    "building rows replayed without its worker: the loop's extra time parted into the rows' "
    "fusion and the worker; see docs/bridge.md.",
    "buildings_ch4_rerender": "The chapter-4 experiment rendered and run again on another "
    "2-core host with the same code and seeds: how far its figures move between renders of the "
    "same drive; see docs/bridge.md.",
    "slam_images": "The SLAM on rendered image sequences (six 600 m drives), georeferenced "
    "without ground truth, against COLMAP. The pass at 69b524d ran beside three test suites "
    "(load 10-13 after its first minutes, although `machine` gives the load at its start), so "
    "its speed keys (`frames_per_second`, `*_ms_*`, `wall_time_over_colmap`) are loaded "
    "figures; the previous pass's idle figure was 17.6 frames/s, the reporting split's 15.4 "
    "(`slam_images_report.json`, load 1.3).",
    "accuracy_real_seg_real_train": "The shipped `seg_real` on CamVid's train split (367 "
    "frames of three sequences; val holds 101 frames of one of them), which no synthetic-only "
    "network trains on: a split to choose among synthetic-only candidates without looking at "
    "val, and a measure of how much one sequence flatters the zero-shot figures; see "
    "docs/lessons.md.",
    "accuracy_real_street": "The joint network `street`, labels learned from CamVid train (one "
    "sequence held out for selection), normals from the randomised city: CamVid val at its "
    "native size, in colour and grey; see docs/real_images.md.",
    "slam_images_report": "The SLAM on images on five 300 m drives of cities never used to "
    "choose a setting (the reporting split), GPS error measured at each fix's own time.",
    "slam_real": "The SLAM on two real KITTI clips (the tuning split) with GPS, odometry and "
    "DEM logs simulated from their true poses, three seeds, four sensor sets; see "
    "bench/slam_real.py.",
    "reloc_real": "Relocalisation of real photographs: the KITTI clips, every other frame a "
    "georeferenced base image and the rest queries, through `geoseg base build` and `geoseg "
    "localize`; see bench/reloc_real.py.",
    "frontend_tracks": "The visual front end's tracks against rendered depth and poses.",
    "buildings_ch4_report": "The chapter-4 experiment, settings unchanged, on five 300 m drives "
    "of cities never used to choose a setting (bench/splits.py's report seeds), synchronous and "
    "as users run it (asynchronous worker): mean, spread and every drive's figures.",
    "colour_transfer_ch4": "The bridge's colour transfer (thesis §4.3.2, `slam run "
    "--colour-transfer card`) on the chapter-4 experiment: five 300 m report drives rendered as "
    "they are and through another camera (a warm white balance, darker mid-tones: outside the "
    "networks' training data), bayes association on both models with and without the transfer; "
    "see docs/bridge.md.",
    "buildings_ch4_occluded": "The chapter-4 experiment's exact model behind occluders "
    "(`bench/buildings_ch4.py --occluded`, its own file: `buildings_ch4.json` is a 1.2 km run "
    "assembled in passes): five 250 m report drives, each in a `facade_occluded` city (1 m "
    "sidewalks, facades on their edge: trees, shelters and parked vehicles within 1-2 m of the "
    "facades, as in the thesis's figure 4.13) and in the chapter-4 city of the same seed; the "
    "ray-cast baseline (the exact model's 1.5 m gate and the GIS model's 3 m) against the "
    "joint network + eq. 4.14, and the wrong associations by class and distance; see "
    "docs/bridge.md.",
    "reloc_slam": "The SLAM started and constrained by an image base (a winter traversal of the "
    "route) instead of or beside a GPS, on five report drives, its keyframes adjusted together "
    "on the base's fixes once the drive is over (before it: the `_loop_` keys, the positions the "
    "loop left, and the `_online_` keys, those it gave each keyframe as it went); see "
    "bench/reloc_slam.py.",
    "gps_bias": "A biased GPS caught by the building model (thesis §4.4): six 150 m "
    "chapter-4 drives never used to choose a setting (seeds 31-36; seed 34's GPS misses most of "
    "its drive, so its biased runs never georeference), GIS model + odometry + DEM + "
    "the simulator's biased receiver (up to 3 m); the SLAM's mean error over the fixes' "
    "(`bias_ratio_*`, target <= 0.5 with buildings) without buildings, with buildings and with "
    "the GPS bias estimated from the facades, and the estimate's cost on an unbiased GPS "
    "(`unbiased_ratio_*`); see docs/bridge.md.",
    "refine": "The global constrained bundle adjustment as a pseudo ground truth (thesis §3.7, "
    "`geoseg slam refine`): three 200 m report drives, each run with a GPS (0.75 m; "
    "`biased_gps_*`: the simulator's biased receiver), odometry, DEM and the GIS building "
    "model, then refined with the same; the refined and the run's keyframes against the truth, "
    "and the run measured against the refined run; see docs/refine.md.",
    "refine_tuning": "The same on the two tuning drives (seeds 40, 44), where the refinement's "
    "settings were chosen.",
    "gps_bias_tuning": "The same on the five tuning drives (seeds 21-25), where the bias "
    "estimate's settings were chosen.",
    "train_speed": "Training step time under thread settings.",
}


# ============================================================================ reading


def load_results(folder: Path = RESULTS) -> dict[str, dict[str, Any]]:
    """``name -> figures`` of every ``folder/*.json`` holding a JSON object (others skipped)."""
    out = {}
    for path in sorted(folder.glob("*.json")):
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            print(f"skipped {path.name}: {err}", file=sys.stderr)
            continue
        if isinstance(data, dict):
            out[path.stem] = data
    return out


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def headline_rows(results: dict[str, dict[str, Any]]) -> list[tuple[str, str, str, str, str]]:
    """``(label, measured, target, thesis, file)`` for each headline figure that is there."""
    rows = []
    for fig in HEADLINE:
        data = results.get(fig.file, {})
        values = [data.get(k) for k in fig.keys]
        if not all(_is_number(v) for v in values):
            continue
        measured = " / ".join(fig.fmt(float(v)) for v in values) + fig.unit
        rows.append((fig.label, measured, fig.target, fig.thesis, fig.file))
    return rows


def _flatten(data: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for k, v in data.items():
        if isinstance(v, dict):
            out += _flatten(v, f"{prefix}{k}.")
        else:
            out.append((f"{prefix}{k}", v))
    return out


def _cell(v: Any) -> str:
    if _is_number(v):
        return f"{v:.4g}" if isinstance(v, float) else str(v)
    if v is None:
        return "-"
    text = json.dumps(v) if isinstance(v, list) else str(v)
    text = text.replace("|", "\\|").replace("\n", " ")
    return text if len(text) <= 120 else text[:117] + "..."


def _about(name: str) -> str:
    if name in ABOUT:
        return ABOUT[name]
    script = ROOT / "bench" / f"{name}.py"
    if script.is_file():
        import ast

        doc = ast.get_docstring(ast.parse(script.read_text())) or ""
        return doc.strip().splitlines()[0] if doc.strip() else ""
    return ""


# ============================================================================ writing


def headline_table(results: dict[str, dict[str, Any]], link: str) -> str:
    """The Markdown headline table; ``link`` prefixes the per-file anchors."""
    lines = [
        "| figure | measured | target | thesis |",
        "|---|---|---|---|",
    ]
    for label, measured, target, thesis, file in headline_rows(results):
        lines.append(f"| [{label}]({link}#{file}) | {measured} | {target} | {thesis} |")
    return "\n".join(lines)


def results_page(results: dict[str, dict[str, Any]]) -> str:
    parts = [
        "# Benchmark results",
        "",
        "Generated by `python docs/make_results.py` from `bench/results/*.json`; do not edit by "
        "hand. Each benchmark is a script `bench/NAME.py` (`geoseg bench NAME`) that prints a "
        "table and writes `bench/results/NAME.json` whole, with the command, commit, machine, "
        "date and data split it ran on (`tests/test_bench_results.py` lists the files that "
        "wait to be re-measured that way). CPU figures come from a shared 2-core machine: "
        "speeds are ratios measured side by side in one run.",
        "",
        "## Headline figures",
        "",
        headline_table(results, ""),
        "",
    ]
    for name, data in results.items():
        parts += [f'<a id="{name}"></a>', "", f"## {name}", ""]
        about = _about(name)
        if about:
            parts += [about, ""]
        for meta in PROVENANCE:
            if meta in data:
                parts.append(f"- {meta}: `{_cell(data[meta])}`")
        parts += ["", "| figure | value |", "|---|---|"]
        for key, value in _flatten(data):
            if key in PROVENANCE:
                continue
            parts.append(f"| `{key}` | {_cell(value)} |")
        parts.append("")
    return "\n".join(parts)


def readme_with_table(readme: str, table: str, begin: str = BEGIN, end: str = END) -> str:
    """``readme`` with the text between its ``begin`` and ``end`` markers replaced by
    ``table``."""
    if begin not in readme or end not in readme:
        raise SystemExit(f"{README}: no {begin} ... {end} block to fill")
    head, rest = readme.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{table}\n{end}{tail}"


# ============================================================================ the demo's paragraph

DEMO_BEGIN, DEMO_END = "<!-- demo:begin -->", "<!-- demo:end -->"
#: how far a run of ``geoseg demo`` may be from ``bench/results/demo.json`` (checked by
#: ``tests/test_readme.py``, stated in the README): the render and the networks' arithmetic
#: differ in their last bits between machines, and a SLAM run amplifies that
DEMO_TOLERANCE = {"score": 0.02, "error_m": 0.02, "error_share": 0.25, "facade_share": 0.05}
DEMO_RULES = (("nobuild", "no buildings"), ("raycast", "geometric rule"), ("bayes", "network"))
DEMO_MODELS = (
    ("exact", "true facades, odometry + road elevation, no GPS"),
    ("gis", "GIS model (facades off by up to 2.5 m), GPS + odometry + road elevation"),
)


def _demo_cell(demo: dict[str, Any], run: str) -> str:
    error = demo.get(f"translation_error_m_{run}")
    if not _is_number(error):
        return "failed"
    cell = f"{error:.3f} m"
    points, right = demo.get(f"associated_points_{run}"), demo.get(f"association_precision_{run}")
    if _is_number(points) and _is_number(right):
        cell += f", {points} points on facades, {100 * right:.0f} % right"
    return cell


def demo_paragraph(results: dict[str, dict[str, Any]]) -> str:
    """The README's text on what ``geoseg demo`` prints, from ``demo.json`` (and the chapter-4
    bench's renders for the long drive)."""
    demo, seg = results.get("demo", {}), results.get("accuracy_seg", {})
    if not demo:
        return "(no `bench/results/demo.json`: run `python bench/demo.py`)"
    tol = DEMO_TOLERANCE
    lines = [
        f"It prints the network's score on the demo frames, `mIoU "
        f"{demo['segmentation_miou']:.2f}, pixel accuracy "
        f"{demo['segmentation_pixel_accuracy']:.2f}`: lower than the held-out benchmark's "
        f"{seg.get('miou', float('nan')):.2f} below because the 40 demo frames hold few pixels "
        "of the small classes (vegetation, poles and signs), where one mistake weighs a lot (the "
        "mIoU is the mean over the 8 classes of intersection over union). Then each SLAM run's "
        "mean error and, for the building rules, how many map points they put on a facade and "
        "the share on the right one:",
        "",
        "| building model | " + " | ".join(name for _, name in DEMO_RULES) + " |",
        "|---" * (len(DEMO_RULES) + 1) + "|",
    ]
    for model, setting in DEMO_MODELS:
        gps = demo.get(f"gps_error_m_nobuild_{model}")
        setting += f" (fixes {gps:.2f} m off)" if _is_number(gps) else ""
        cells = [_demo_cell(demo, f"{rule}_{model}") for rule, _ in DEMO_RULES]
        lines.append(f"| {setting} | " + " | ".join(cells) + " |")
    long_drive = [
        (results.get(name, {}).get("translation_error_m_nobuild_gis"),
         results.get(name, {}).get("translation_error_m_bayes_gis"))
        for name in ("buildings_ch4", "buildings_ch4_rerender")
    ]  # fmt: skip
    renders = " and ".join(
        f"{without:.3f} m -> {network:.3f} m"
        for without, network in long_drive
        if _is_number(without) and _is_number(network)
    )
    lines += [
        "",
        "With the true facades the building rules hold the trajectory on the facades; with the "
        "GIS model beside a GPS they move the error little on so short a drive. Over 1.2 km the "
        f"network's rule moved the GIS error ({renders} on two renders of the drive, without "
        "buildings -> with the network's): with such a model and a GPS the building rows move "
        "the error by a few centimetres either way ([the bridge's results]"
        "(docs/bridge.md#the-chapter-4-experiment)).",
        "",
        "These figures are `bench/results/demo.json`, which `python bench/demo.py` writes from a "
        "run of the demo (its own `geoseg_demo/demo.json`); `tests/test_readme.py` runs the demo "
        f"and checks what it prints against them: scores within {tol['score']}, errors within "
        f"{tol['error_m']} m or {100 * tol['error_share']:.0f} %, whichever is larger, shares "
        f"on the right facade within {100 * tol['facade_share']:.0f} points. The last digits "
        "differ between machines (the render and the networks' arithmetic differ in their last "
        "bits, and a SLAM run amplifies that).",
    ]
    wrap = textwrap.TextWrapper(width=96, break_long_words=False, break_on_hyphens=False)
    return "\n".join(line if line.startswith("|") else wrap.fill(line) for line in lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="exit 1 when a file is out of date")
    args = p.parse_args(argv)
    results = load_results()
    page = results_page(results)
    readme = readme_with_table(README.read_text(), headline_table(results, "docs/results.md"))
    readme = readme_with_table(readme, demo_paragraph(results), DEMO_BEGIN, DEMO_END)
    if args.check:
        stale = [
            path
            for path, text in ((PAGE, page), (README, readme))
            if not path.is_file() or path.read_text() != text
        ]
        for path in stale:
            print(f"{path.relative_to(ROOT)} is out of date: run python docs/make_results.py")
        return 1 if stale else 0
    PAGE.write_text(page)
    README.write_text(readme)
    print(f"written {PAGE.relative_to(ROOT)} and the README's results table and demo figures")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

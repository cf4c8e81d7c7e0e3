"""Inference speed of the joint labels + normals network vs torchvision's LRASPP-MobileNetV3.

Contenders, at 640x480, batch 1, on the CPU, measured side by side in one run (warm-up, then
interleaved rounds, median per contender):

- ``lraspp_torch``: ``lraspp_mobilenet_v3_large(weights=None, weights_backbone=None,
  num_classes=8)`` in torch eager (what a user would pick instead; no downloads);
- ``joint_torch``: the joint network in torch eager;
- ``joint_ort``: the joint network exported with :func:`geoseg.export.export_onnx`, onnxruntime
  session fixed to the frame size (batch 1, 640x480: ``OnnxModel(..., fixed_dims=...)``, as
  ``Segmenter.from_onnx(..., frame_size=...)`` opens it for a camera), which lets onnxruntime
  plan memory and kernels for that size;
- ``joint_ort_dynamic``: the same file in a session with dynamic batch and size (any input), as
  are the sessions below;
- ``joint_ort_plain``: the same exported without :mod:`geoseg.export_rewrites` (``rewrite=False``),
  to show what the rewrites buy;
- ``joint_ort_int8``: the same, statically quantised to int8 (QDQ, per-channel weights) with
  ``onnxruntime.quantization`` (calibration below);
- ``enet_ort``: the plain ENet on onnxruntime, for reference;
- ``lraspp_ort``: LRASPP exported the same way (fixed size), for an onnxruntime-to-onnxruntime
  comparison (``ort_over_lraspp_ort_640x480``).

Weights: the shipped trained networks (``geoseg/weights/normals`` and ``.../seg``) when present
(``--weights random``: untrained, timing only). With trained weights the int8 model is calibrated
on frames of the validation city and ``int8_miou_change`` is its mIoU minus fp32's on held-out
frames of the evaluation city at 320x240, the networks' training size; on the same frames the
fp32 export is compared with the torch model (``onnx_torch_label_agreement_heldout``,
``onnx_torch_normal_angle_deg_heldout``, ``torch_miou_heldout``). Always reported: label
agreement (argmax) and mean normal angle between int8 and fp32 on smooth random inputs.

With CUDA available (or ``--gpu-only`` on the GPU machine, merged into the results file) it
measures batch-1 latency and batch-8 throughput at 640x480 in several modes: eager fp32/fp16,
channels-last, replay from a CUDA graph, and with ``--compile`` ``torch.compile`` (Inductor with
CUDA graphs); ``gpu_batch1_ms_640x480`` is the best mode's (``gpu_batch1_mode`` names it).

Usage::

    python bench/inference_speed.py            # a few minutes on 2 CPU cores
    python bench/inference_speed.py --full     # more repetitions
    python bench/inference_speed.py --gpu-only --compile   # on a CUDA machine

Per-operator kernel times of ``joint_ort`` and ``lraspp_ort`` from onnxruntime's profiler
(``ops_<model>_ort_<Op>_ms``, :mod:`bench/ort_operators.py`, the two profiled in turn) and the
convolutions' multiply-accumulates (``<model>_gmac_640x480``) say where the time goes
(docs/onnx_operators.md). The same two files are also timed by the CPU time of the calling
thread with one intra-op thread, interleaved (``<model>_ort_cpu_1thread_ms_640x480``, medians;
``ort_over_lraspp_ort_cpu_1thread_640x480``): on a host shared with other jobs the wall times
swing by 2x between rounds while the CPU times hold.

Prints a Markdown table and writes ``bench/results/inference_speed.json`` (medians as
``<contender>_ms_640x480``, minima as ``<contender>_min_ms_640x480``; the 1-minute load average
is recorded). Each timed call follows an untimed call of the same contender: onnxruntime's and
OpenMP's worker threads keep spinning for a while after a call, and timing a contender right after
another one measured that contention (earlier versions of this script did, which inflated torch
eager's times by ~40 % and flattered every ratio to LRASPP). The onnxruntime sessions also stop
spinning when a call returns (:class:`geoseg.export.OnnxModel`'s default).

This project's 2-core VM runs at about half speed in phases of tens of seconds (its host's doing:
the joint network on onnxruntime went from 59 to 131 ms per call after 24 s of back-to-back calls,
and back after a rest; the script rests ``--rest`` seconds after its exports and quantisation
before timing, and after each round as long as the round took). A slow phase adds time to every
contender, not in proportion
(onnxruntime's threads suffer more than torch's), so the headline ratio
``ort_over_lraspp_640x480`` compares the contenders' *minima* (their unthrottled speeds); the
ratio of medians is kept as ``ort_over_lraspp_median_640x480``, trustworthy only when the medians
sit near the minima.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

RESULTS = Path(__file__).resolve().parent / "results" / "inference_speed.json"
if str(Path(__file__).resolve().parent) not in sys.path:  # bench/ort_operators.py
    sys.path.insert(0, str(Path(__file__).resolve().parent))
H, W = 480, 640


def smooth_images(n: int, seed: int) -> list[np.ndarray]:
    """`(1, 3, H, W)` float32 inputs: upsampled Gaussian noise (image-like spatial correlation)."""
    import cv2

    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        small = rng.standard_normal((3, H // 8, W // 8)).astype(np.float32)
        out.append(
            np.stack([cv2.resize(c, (W, H), interpolation=cv2.INTER_CUBIC) for c in small])[None]
        )
    return out


def load_trained(joint: torch.nn.Module, enet: torch.nn.Module) -> bool:
    """Load the shipped weights (geoseg/weights/normals, .../seg) into the models, when present."""
    from geoseg.errors import GeosegError
    from geoseg.infer import load_model_checkpoint
    from geoseg.pretrained import pretrained_file

    try:
        joint_file, enet_file = pretrained_file("normals"), pretrained_file("seg")
    except GeosegError as err:
        print(f"untrained models (timing only): {err}")
        return False
    joint.load_state_dict(load_model_checkpoint(joint_file)[0].state_dict())
    enet.load_state_dict(load_model_checkpoint(enet_file)[0].state_dict())
    return True


# The shipped networks are trained on 320x240 frames: int8's accuracy is measured at that size.
ACCURACY_HW = (240, 320)


def synthetic_frames(split: str, n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``n`` normalised `(1, 3, h, w)` frames and their `(h, w)` labels at :data:`ACCURACY_HW`.

    ``split="test"``: the held-out evaluation city (every condition, as bench/accuracy_seg.py);
    ``"val"``: the validation city (calibration data that the evaluation never sees).
    """
    from training.evaluate_seg import EvalConfig, heldout_dataset, heldout_indices
    from training.frame_data import NormalizeImage

    if split == "test":
        ds = heldout_dataset(EvalConfig(frames=n, size=ACCURACY_HW, progress=False))
        indices = heldout_indices(ds, n)
    else:
        from geoseg.data.synthetic import SyntheticDataset, synthetic_config

        ds = SyntheticDataset(synthetic_config({}, split="val"), size=ACCURACY_HW)
        indices = list(range(n))
    normalize = NormalizeImage()
    images, labels = [], []
    for i in indices:
        sample = ds[i]
        images.append(normalize(sample)["image"][None].numpy())
        labels.append(sample["labels"].numpy())
    return images, labels


def miou(pred: list[np.ndarray], truth: list[np.ndarray]) -> float:
    """mIoU (:func:`training.metrics.segmentation_scores`) of 8-class label maps."""
    from training.metrics import confusion_matrix, segmentation_scores

    cm = sum(
        confusion_matrix(torch.from_numpy(p.astype(np.int64)), torch.from_numpy(t))
        for p, t in zip(pred, truth, strict=True)
    )
    return segmentation_scores(cm)["miou"]


def quantize_int8(src: Path, dst: Path, calibration: list[np.ndarray], input_name: str) -> None:
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.items = iter([{input_name: x} for x in calibration])

        def get_next(self):
            return next(self.items, None)

    quantize_static(
        str(src),
        str(dst),
        Reader(),
        quant_format=QuantFormat.QDQ,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        per_channel=True,
    )
    # the quantiser copies the fp32 file's metadata, its content digest included: record the
    # int8 file's own (geoseg.export.verify_onnx_file checks it on opening)
    import onnx

    from geoseg.export import DIGEST_PROP, META_PREFIX, onnx_content_sha256

    proto = onnx.load(str(dst))
    for prop in proto.metadata_props:
        if prop.key == META_PREFIX + DIGEST_PROP:
            prop.value = onnx_content_sha256(proto)
    onnx.save(proto, str(dst))


def time_interleaved(
    contenders: dict[str, Callable[[], object]], *, warmup: int, repeats: int, rest: float = 1.0
) -> dict[str, list[float]]:
    """Milliseconds per call (one list per contender), contenders interleaved round by round.

    Each timed call follows an untimed one of the same contender, so that no call is timed while
    the previous contender's worker threads still spin. After each round the machine idles for
    ``rest`` times the round's duration (the host throttles long full loads; module docstring).
    """
    for fn in contenders.values():
        for _ in range(warmup):
            fn()
    samples: dict[str, list[float]] = {k: [] for k in contenders}
    for _ in range(repeats):
        start = time.perf_counter()
        for name, fn in contenders.items():
            fn()
            t0 = time.perf_counter()
            fn()
            samples[name].append((time.perf_counter() - t0) * 1e3)
        time.sleep(rest * (time.perf_counter() - start))
    return samples


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((a * b).sum(1), -1.0, 1.0))).mean())


def _cuda_latency_ms(fn: Callable[[], object], iters: int) -> float:
    """Median wall time of ``fn`` on CUDA, one synchronised call per sample, in ms."""
    times = []
    for _ in range(iters):
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _cuda_graph_call(net: torch.nn.Module, x: torch.Tensor) -> Callable[[], object]:
    """Capture ``net(x)`` in a CUDA graph (after warm-up on a side stream); returns the replay."""
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream), torch.inference_mode():
        for _ in range(3):
            net(x)
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.inference_mode(), torch.cuda.graph(graph):
        net(x)
    return graph.replay


def cuda_figures(model: torch.nn.Module, repeats: int, compile_model: bool) -> dict[str, object]:
    """Batch-1 latency and batch-8 throughput at 640x480 on CUDA, several execution modes.

    Modes: eager fp32, eager fp16, fp16 channels-last, fp16 replayed from a CUDA graph (the
    launch overhead of ENet's ~300 small kernels dominates at batch 1), and, with
    ``compile_model``, ``torch.compile(mode="reduce-overhead")`` (Inductor kernels replayed
    from CUDA graphs).
    ``gpu_batch1_ms_640x480`` / ``gpu_batch8_fps_640x480`` are the best mode's.
    """
    dev = torch.device("cuda")
    iters = max(repeats * 20, 200)
    base = model.to(dev).eval()
    modes: dict[str, tuple[torch.nn.Module, torch.dtype, torch.memory_format, str]] = {
        "eager_fp32": (base, torch.float32, torch.contiguous_format, "eager"),
    }
    half = copy.deepcopy(base).half()
    modes["eager_fp16"] = (half, torch.half, torch.contiguous_format, "eager")
    half_cl = copy.deepcopy(half).to(memory_format=torch.channels_last)
    modes["eager_fp16_channels_last"] = (half_cl, torch.half, torch.channels_last, "eager")
    modes["cudagraph_fp16"] = (half, torch.half, torch.contiguous_format, "graph")
    modes["cudagraph_fp16_channels_last"] = (half_cl, torch.half, torch.channels_last, "graph")
    if compile_model:
        compiled = torch.compile(half, mode="reduce-overhead")
        modes["compile_fp16"] = (compiled, torch.half, torch.contiguous_format, "eager")
    figures: dict[str, object] = {}
    for name, (net, dtype, fmt, how) in modes.items():
        for batch in (1, 8):
            x = torch.randn(batch, 3, H, W, device=dev, dtype=dtype).contiguous(memory_format=fmt)
            try:
                if how == "graph":
                    call = _cuda_graph_call(net, x)
                else:

                    def call(net=net, x=x) -> object:
                        with torch.inference_mode():
                            return net(x)

                    for _ in range(10):  # warm-up (and compilation)
                        call()
                torch.cuda.synchronize()
                ms = _cuda_latency_ms(call, iters)
            except Exception as exc:  # a mode that fails is reported, not fatal
                print(f"CUDA mode {name} batch {batch} failed: {type(exc).__name__}: {exc}")
                continue
            figures[f"gpu_{name}_batch{batch}_ms_640x480"] = ms
            print(
                f"CUDA {name:30s} batch {batch}: {ms:7.3f} ms  ({1e3 * batch / ms:8.1f} images/s)"
            )
    b1 = {k: v for k, v in figures.items() if k.endswith("batch1_ms_640x480")}
    b8 = {k: v for k, v in figures.items() if k.endswith("batch8_ms_640x480")}
    best1 = min(b1, key=b1.get)
    best8 = min(b8, key=b8.get)
    figures["gpu_batch1_ms_640x480"] = b1[best1]
    figures["gpu_batch1_mode"] = best1[len("gpu_") : -len("_batch1_ms_640x480")]
    figures["gpu_batch8_fps_640x480"] = 8e3 / b8[best8]
    figures["gpu_batch8_mode"] = best8[len("gpu_") : -len("_batch8_ms_640x480")]
    figures["gpu_name"] = torch.cuda.get_device_name(0)
    figures["gpu_torch"] = torch.__version__
    return figures


def gpu_only(args: argparse.Namespace) -> int:
    """Measure the CUDA figures alone and merge them into ``args.out`` (CPU figures kept)."""
    from geoseg.models import get_model

    if not torch.cuda.is_available():
        print("--gpu-only: no CUDA device")
        return 1
    torch.manual_seed(0)
    joint = get_model("joint", num_classes=8).eval()
    figures = cuda_figures(joint, repeats=25 if args.full else 10, compile_model=args.compile)
    results = json.loads(args.out.read_text()) if args.out.is_file() else {}
    results.update(figures)
    results["gpu_command"] = " ".join(["python", "bench/inference_speed.py", *sys.argv[1:]])
    print(
        f"CUDA ({figures['gpu_name']}): batch 1 {figures['gpu_batch1_ms_640x480']:.3f} ms "
        f"({figures['gpu_batch1_mode']}), batch 8 {figures['gpu_batch8_fps_640x480']:.0f} "
        f"images/s ({figures['gpu_batch8_mode']}); target batch 1 <= 2 ms on an H100"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="more repetitions")
    parser.add_argument(
        "--rest",
        type=float,
        default=45.0,
        help="seconds idle between the exports and the timing, so that the timing does not start "
        "in a throttled phase (see the module docstring)",
    )
    parser.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--weights",
        choices=("shipped", "random"),
        default="shipped",
        help="shipped: the trained weights in geoseg/weights when present (int8 mIoU change on "
        "held-out frames); random: untrained models, timing only",
    )
    parser.add_argument(
        "--accuracy-frames", type=int, default=16, help="held-out frames for int8_miou_change"
    )
    parser.add_argument(
        "--gpu-only", action="store_true", help="CUDA figures only, merged into --out"
    )
    parser.add_argument(
        "--compile", action="store_true", help="also time torch.compile on CUDA (minutes)"
    )
    args = parser.parse_args(argv)
    if args.gpu_only:
        return gpu_only(args)

    import onnxruntime as ort
    from torchvision.models.segmentation import lraspp_mobilenet_v3_large

    from geoseg.export import OnnxModel, export_onnx
    from geoseg.models import count_parameters, get_model

    warmup, repeats = (3, 25) if args.full else (2, 7)
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    joint = get_model("joint", num_classes=8).eval()
    enet = get_model("enet", num_classes=8).eval()
    trained = load_trained(joint, enet) if args.weights == "shipped" else False
    lraspp = lraspp_mobilenet_v3_large(weights=None, weights_backbone=None, num_classes=8).eval()

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        export_onnx(joint, tmp / "joint.onnx")
        export_onnx(joint, tmp / "joint_plain.onnx", rewrite=False)
        export_onnx(enet, tmp / "enet.onnx")
        export_onnx(
            lraspp, tmp / "lraspp.onnx", example_inputs=torch.zeros(1, 3, H, W), dynamic=False
        )
        if trained:  # calibrate on real frames of the validation city
            calibration = synthetic_frames("val", 8)[0]
        else:
            calibration = smooth_images(4, seed=1)
        quantize_int8(tmp / "joint.onnx", tmp / "joint_int8.onnx", calibration, "x")
        cpu = ["CPUExecutionProvider"]
        frame = {"batch": 1, "height": H, "width": W}
        joint_ort = OnnxModel(
            tmp / "joint.onnx", providers=cpu, threads=args.threads, fixed_dims=frame
        )
        joint_dynamic = OnnxModel(tmp / "joint.onnx", providers=cpu, threads=args.threads)
        joint_plain = OnnxModel(tmp / "joint_plain.onnx", providers=cpu, threads=args.threads)
        joint_int8 = OnnxModel(tmp / "joint_int8.onnx", providers=cpu, threads=args.threads)
        enet_ort = OnnxModel(tmp / "enet.onnx", providers=cpu, threads=args.threads)
        lraspp_ort = OnnxModel(tmp / "lraspp.onnx", providers=cpu, threads=args.threads)

        x_np = smooth_images(1, seed=2)[0]
        x = torch.from_numpy(x_np)

        def torch_call(model: torch.nn.Module) -> Callable[[], object]:
            def call() -> object:
                with torch.inference_mode():
                    return model(x)

            return call

        contenders = {
            "lraspp_torch": torch_call(lraspp),
            "joint_torch": torch_call(joint),
            "joint_ort": lambda: joint_ort(x_np),
            "joint_ort_dynamic": lambda: joint_dynamic(x_np),
            "joint_ort_plain": lambda: joint_plain(x_np),
            "joint_ort_int8": lambda: joint_int8(x_np),
            "enet_ort": lambda: enet_ort(x_np),
            "lraspp_ort": lambda: lraspp_ort(x_np),
        }
        time.sleep(args.rest)
        samples = time_interleaved(contenders, warmup=warmup, repeats=repeats)
        ms = {k: statistics.median(v) for k, v in samples.items()}
        ms_min = {k: min(v) for k, v in samples.items()}

        # where the time goes: onnxruntime's per-operator kernel times (docs/onnx_operators.md)
        from ort_operators import count_macs, cpu_time_interleaved, operator_breakdowns

        names = ("joint", "lraspp")
        breakdown = dict(
            zip(
                names,
                operator_breakdowns(
                    [tmp / f"{n}.onnx" for n in names],
                    threads=args.threads,
                    fixed_dims=frame,
                    calls=repeats,
                ),
            )
        )
        # the same two files timed by the CPU time of one thread (immune to a shared host's
        # descheduling, which swings the wall times above by 2x)
        cpu_ms = dict(
            zip(
                names,
                (
                    statistics.median(t)
                    for t in cpu_time_interleaved(
                        [tmp / f"{n}.onnx" for n in names], fixed_dims=frame, rounds=2 * repeats
                    )
                ),
            )
        )

        agreement, angles, majority = [], [], []
        for img in smooth_images(3, seed=3):
            ref, q = joint_dynamic(img), joint_int8(img)
            labels = ref["logits"].argmax(1)
            agreement.append(float((q["logits"].argmax(1) == labels).mean()))
            angles.append(angle_deg(q["normals"], ref["normals"]))
            majority.append(float(np.bincount(labels.ravel(), minlength=8).max() / labels.size))
        accuracy: dict[str, float] = {}
        if trained:
            images, truth = synthetic_frames("test", args.accuracy_frames)
            fp32_out = [joint_dynamic(x) for x in images]
            fp32 = [out["logits"].argmax(1)[0] for out in fp32_out]
            int8 = [joint_int8(x)["logits"].argmax(1)[0] for x in images]
            # the rewritten export against the torch model it came from, on the same frames
            with torch.inference_mode():
                eager = [joint(torch.from_numpy(x)) for x in images]
            eager_labels = [out["logits"].argmax(1)[0].numpy() for out in eager]
            accuracy = {
                "onnx_torch_label_agreement_heldout": float(
                    np.mean([np.mean(a == b) for a, b in zip(fp32, eager_labels)])
                ),
                "onnx_torch_normal_angle_deg_heldout": float(
                    np.mean(
                        [
                            angle_deg(out["normals"], ref["normals"].numpy())
                            for out, ref in zip(fp32_out, eager)
                        ]
                    )
                ),
                "torch_miou_heldout": miou(eager_labels, truth),
                "fp32_miou_heldout": miou(fp32, truth),
                "int8_miou_heldout": miou(int8, truth),
                "accuracy_frames": args.accuracy_frames,
            }
            accuracy["int8_miou_change"] = (
                accuracy["int8_miou_heldout"] - accuracy["fp32_miou_heldout"]
            )

    results: dict[str, object] = {
        "enet_params": count_parameters(enet),
        "joint_params": count_parameters(joint),
        "normals_head_params": count_parameters(joint.normal_head),
        "normals_head_overhead_pct": 100.0
        * count_parameters(joint.normal_head)
        / count_parameters(enet),
        "lraspp_params": count_parameters(lraspp),
        **{f"{k}_ms_640x480": v for k, v in ms.items()},
        **{f"{k}_min_ms_640x480": v for k, v in ms_min.items()},
        # ratios of minima (see the module docstring), the headline's also of medians
        "ort_over_lraspp_640x480": ms_min["joint_ort"] / ms_min["lraspp_torch"],
        "ort_over_lraspp_median_640x480": ms["joint_ort"] / ms["lraspp_torch"],
        "ort_dynamic_over_lraspp_640x480": ms_min["joint_ort_dynamic"] / ms_min["lraspp_torch"],
        "fixed_over_dynamic_ort_640x480": ms_min["joint_ort"] / ms_min["joint_ort_dynamic"],
        "ort_over_lraspp_ort_640x480": ms_min["joint_ort"] / ms_min["lraspp_ort"],
        "joint_ort_cpu_1thread_ms_640x480": cpu_ms["joint"],
        "lraspp_ort_cpu_1thread_ms_640x480": cpu_ms["lraspp"],
        "ort_over_lraspp_ort_cpu_1thread_640x480": cpu_ms["joint"] / cpu_ms["lraspp"],
        "joint_torch_over_lraspp_640x480": ms_min["joint_torch"] / ms_min["lraspp_torch"],
        "int8_over_fp32_ort_640x480": ms_min["joint_ort_int8"] / ms_min["joint_ort_dynamic"],
        "rewritten_over_plain_ort_640x480": ms_min["joint_ort_dynamic"] / ms_min["joint_ort_plain"],
        "int8_label_agreement": float(np.mean(agreement)),
        "int8_normal_angle_deg": float(np.mean(angles)),
        "fp32_majority_label_fraction": float(np.mean(majority)),
        **accuracy,
        "joint_gmac_640x480": count_macs(joint, torch.zeros(1, 3, H, W)) / 1e9,
        "enet_gmac_640x480": count_macs(enet, torch.zeros(1, 3, H, W)) / 1e9,
        "lraspp_gmac_640x480": count_macs(lraspp, torch.zeros(1, 3, H, W)) / 1e9,
        **{
            f"ops_{name}_ort_{op}_ms": ms_op
            for name, table in breakdown.items()
            for op, ms_op in table.items()
        },
        "trained_weights": trained,
        "threads": args.threads,
        "repeats": repeats,
    }
    if torch.cuda.is_available():
        results.update(cuda_figures(joint, repeats, compile_model=args.compile))
    elif args.out.is_file():  # keep the figures a GPU machine measured (--gpu-only)
        previous = json.loads(args.out.read_text())
        gpu = {k: v for k, v in previous.items() if k.startswith("gpu_")}
        results.update(gpu)
        if gpu:  # a pass that reuses an earlier run's figures says which
            results["gpu_figures_from"] = previous.get(
                "gpu_figures_from",
                f"kept from the file this run replaced ({previous.get('date', 'undated')}, "
                f"{previous.get('git_commit', 'unknown commit')})",
            )
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    results["load_average_1min"] = load
    results["machine"] = (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
        f"torch {torch.__version__}, onnxruntime {ort.__version__}, python {platform.python_version()}"
    )
    results["command"] = " ".join(["python", "bench/inference_speed.py", *(argv or sys.argv[1:])])
    from provenance import git_commit

    results["git_commit"] = git_commit()
    results["date"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    results["split"] = "timing on a smooth random 640x480 image; int8 accuracy: held-out city"

    print(
        f"\n## Inference speed, {W}x{H}, batch 1, CPU ({args.threads} threads, {repeats} timed calls each)\n"
    )
    print("| contender | params | median ms | min ms | min / LRASPP torch min |")
    print("|---|---:|---:|---:|---:|")
    params = {
        "lraspp_torch": results["lraspp_params"],
        "joint_torch": results["joint_params"],
        "joint_ort": results["joint_params"],
        "joint_ort_dynamic": results["joint_params"],
        "joint_ort_plain": results["joint_params"],
        "joint_ort_int8": results["joint_params"],
        "enet_ort": results["enet_params"],
        "lraspp_ort": results["lraspp_params"],
    }
    for name, value in ms.items():
        ratio = ms_min[name] / ms_min["lraspp_torch"]
        print(f"| {name} | {params[name]:,} | {value:.1f} | {ms_min[name]:.1f} | {ratio:.2f} |")
    if "int8_miou_change" in results:
        print(
            f"\nint8 on {args.accuracy_frames} held-out frames (trained weights): mIoU "
            f"{results['int8_miou_heldout']:.4f} vs fp32 {results['fp32_miou_heldout']:.4f} "
            f"(change {results['int8_miou_change']:+.4f})"
        )
        print(
            "rewritten ONNX against torch on the same frames: label agreement "
            f"{results['onnx_torch_label_agreement_heldout']:.6f}, mean normal angle "
            f"{results['onnx_torch_normal_angle_deg_heldout']:.4f} deg, mIoU "
            f"{results['fp32_miou_heldout']:.4f} against torch's {results['torch_miou_heldout']:.4f}"
        )
    print(
        f"\nint8 vs fp32 ({'trained' if trained else 'random'} weights, smooth random inputs): "
        "label agreement "
        f"{results['int8_label_agreement']:.4f} (majority class covers "
        f"{results['fp32_majority_label_fraction']:.2f} of the pixels), mean normal angle "
        f"{results['int8_normal_angle_deg']:.2f} deg"
    )
    print(
        f"target joint_ort <= 0.8 x lraspp_torch: {results['ort_over_lraspp_640x480']:.2f} "
        f"(minima), {results['ort_over_lraspp_median_640x480']:.2f} (medians)"
    )
    print(
        "target joint_ort <= 1.0 x lraspp_ort: "
        f"{results['ort_over_lraspp_ort_640x480']:.2f} (wall minima, {args.threads} threads), "
        f"{results['ort_over_lraspp_ort_cpu_1thread_640x480']:.2f} (CPU time medians, 1 thread: "
        f"{cpu_ms['joint']:.1f} ms against {cpu_ms['lraspp']:.1f} ms)"
    )
    if "gpu_batch1_ms_640x480" in results:
        print(
            f"CUDA ({results['gpu_name']}): batch 1 {results['gpu_batch1_ms_640x480']:.3f} ms "
            f"({results['gpu_batch1_mode']}), batch 8 "
            f"{results['gpu_batch8_fps_640x480']:.0f} images/s ({results['gpu_batch8_mode']})"
        )
    print(f"load average (1 min) during the run: {load:.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

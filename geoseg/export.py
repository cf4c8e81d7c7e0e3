"""ONNX export (``torch.onnx.export(..., dynamo=True)``) and onnxruntime sessions with the model's
call signature.

:func:`export_onnx` writes a model with a dynamic batch and (when the model allows it) dynamic
image size, and stores in the ONNX metadata the output names, the model name and configuration
and the input normalisation (keys ``geoseg.*``), and ``geoseg.sha256``, the SHA-256 of the rest
of the file (:func:`onnx_content_sha256`), which :class:`OnnxModel` verifies before running it. Models with ``(B, C, H, W)`` inputs pad
internally, so any ``H, W >= 1`` is accepted by the exported graph as by the torch model. The
naive CNN is exported in its dense form (:class:`~geoseg.models.naive_cnn.NaiveDense`, whole
images to per-pixel log-probabilities).

:class:`OnnxModel` wraps an ``onnxruntime.InferenceSession`` and returns the same named dict as
the torch module (NumPy arrays for NumPy inputs, CPU tensors for tensor inputs).

ENet-based models are exported through :func:`geoseg.export_rewrites.rewrite_for_onnxruntime`
(PReLU, pooling switches, sub-pixel transposed convolutions in the forms onnxruntime's CPU
provider runs in its blocked layout; equal up to float rounding); ``rewrite=False`` exports the
modules as they are.

The legacy TorchScript-based exporter cannot export ``MaxUnpool2d`` with dynamic sizes (with
``rewrite=False``), hence the dynamo exporter. Near-ties in a max-pooling window may flip single
pixels between torch and onnxruntime: compare outputs by argmax agreement and mean errors, not
max-abs equality.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from geoseg.atomic import atomic_write
from geoseg.errors import GeosegError
from geoseg.integrity import corrupt_error, verify_file_against_card

logger = logging.getLogger(__name__)

META_PREFIX = "geoseg."
DIGEST_PROP = "sha256"
FEATURE_CHANNELS = 128


def onnx_content_sha256(proto: Any) -> str:
    """Hex SHA-256 of an ONNX ``ModelProto``'s deterministic serialisation, without its
    ``geoseg.sha256`` metadata property."""
    import hashlib

    import onnx

    copy = onnx.ModelProto()
    copy.CopyFrom(proto)
    kept = [p for p in copy.metadata_props if p.key != META_PREFIX + DIGEST_PROP]
    del copy.metadata_props[:]
    copy.metadata_props.extend(kept)
    return hashlib.sha256(copy.SerializeToString(deterministic=True)).hexdigest()


def verify_onnx_file(path: str | os.PathLike) -> None:
    """Check an ONNX file against its ``geoseg.sha256`` (else the model card next to it).

    Raises:
        GeosegError: the file is not a readable ONNX model, or its content does not match the
            recorded SHA-256 (the message names the file).
    """
    import onnx

    try:
        proto = onnx.load(str(path), load_external_data=False)
    except Exception as err:  # protobuf's DecodeError and friends
        raise GeosegError(
            f"{path}: not a valid ONNX model, corrupt or truncated ({type(err).__name__}: "
            f"{str(err)[:160]})"
        ) from None
    recorded = {p.key: p.value for p in proto.metadata_props}.get(META_PREFIX + DIGEST_PROP)
    if recorded is None:
        verify_file_against_card(path)
        return
    actual = onnx_content_sha256(proto)
    if actual != recorded:
        raise corrupt_error(path, recorded, actual, where="in its metadata (geoseg.sha256)")


def _forward_arg_names(model: nn.Module, count: int) -> list[str]:
    params = [
        p.name
        for p in inspect.signature(model.forward).parameters.values()
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
    ]
    return params[:count] if len(params) >= count else [f"input_{i}" for i in range(count)]


def prepare_for_export(model: nn.Module, *, rewrite: bool = True) -> nn.Module:
    """The module that is exported for ``model``: the naive CNN becomes its dense form, and with
    ``rewrite`` a model with ENet blocks or PReLUs becomes a rewritten copy
    (:func:`~geoseg.export_rewrites.rewrite_for_onnxruntime`; ``model`` itself is untouched)."""
    from geoseg.export_rewrites import rewrite_for_onnxruntime
    from geoseg.models.naive_cnn import NaiveCNN, NaiveDense

    if isinstance(model, NaiveCNN):
        return NaiveDense(model)
    return rewrite_for_onnxruntime(model) if rewrite else model


def default_example_inputs(
    model: nn.Module, *, batch: int = 1, height: int = 64, width: int = 48
) -> tuple[torch.Tensor, ...]:
    """Example inputs for a geoseg model: an image, or layer-21 features for the heads.

    Args:
        model: an ENet, joint, naive CNN (or its dense form), relocalisation or relative-pose head.
        batch, height, width: example size (image pixels; features are ``ceil(size / 8)``).

    Returns:
        ``((batch, 3, height, width),)`` for image models, ``((batch, 128, h, w),)`` for the
        relocalisation head, two such tensors for the relative-pose head.
    """
    from geoseg.models.enet import ENet
    from geoseg.models.joint import JointNet
    from geoseg.models.naive_cnn import NaiveCNN, NaiveDense

    gen = torch.Generator().manual_seed(0)
    if isinstance(model, ENet | JointNet | NaiveCNN | NaiveDense):
        channels = getattr(model, "in_channels", None) or model.net.in_channels
        return (torch.randn(batch, channels, height, width, generator=gen),)
    n_inputs = len(
        [
            p
            for p in inspect.signature(model.forward).parameters.values()
            if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty
        ]
    )
    channels = int(getattr(model, "in_channels", FEATURE_CHANNELS))
    shape = (batch, channels, -(-height // 8), -(-width // 8))
    if n_inputs in (1, 2):
        return tuple(torch.randn(*shape, generator=gen) for _ in range(n_inputs))
    raise GeosegError(f"model: cannot guess example inputs for {type(model).__name__}; pass them")


def _dynamic_shapes(
    names: Sequence[str], inputs: Sequence[torch.Tensor], spatial: bool
) -> dict[str, dict[int, Any]]:
    batch = torch.export.Dim("batch", min=1, max=1024)
    height = torch.export.Dim("height", min=1, max=8192)
    width = torch.export.Dim("width", min=1, max=8192)
    shapes: dict[str, dict[int, Any]] = {}
    for name, x in zip(names, inputs):
        dims: dict[int, Any] = {0: batch}
        if spatial and x.dim() == 4:
            dims.update({2: height, 3: width})
        shapes[name] = dims
    return shapes


@contextlib.contextmanager
def _quiet_exporter_logs(level: int = logging.ERROR):
    """Silence the exporter's chatty INFO/WARNING logs (restored afterwards)."""
    names = ("onnx_ir", "onnxscript", "torch.onnx", "torch.export")
    saved = {n: logging.getLogger(n).level for n in names}
    try:
        for n in names:
            logging.getLogger(n).setLevel(level)
        yield
    finally:
        for n, lvl in saved.items():
            logging.getLogger(n).setLevel(lvl)


def export_onnx(
    model: nn.Module,
    path: str | os.PathLike,
    *,
    example_inputs: torch.Tensor | Sequence[torch.Tensor] | None = None,
    dynamic: bool = True,
    metadata: Mapping[str, Any] | None = None,
    opset: int | None = None,
    rewrite: bool = True,
) -> Path:
    """Export ``model`` to ONNX with the dynamo exporter, in eval mode, on CPU.

    Args:
        model: a geoseg model (or any module returning a dict of tensors). A
            :class:`~geoseg.models.naive_cnn.NaiveCNN` is exported in its dense form.
        path: output ``.onnx`` file (written atomically; parent directories created).
        example_inputs: one tensor or a sequence of tensors, e.g. `(B, 3, H, W)` images;
            default :func:`default_example_inputs`.
        dynamic: dynamic batch and (for 4-D inputs) height and width. When the model cannot be
            exported with a dynamic image size, it falls back to a dynamic batch only and logs
            a warning (recorded as ``geoseg.dynamic_spatial`` in the metadata).
        metadata: extra values stored in the ONNX metadata under ``geoseg.<key>`` (JSON-encoded
            unless already strings), e.g. ``model_name``, ``model_config``, ``normalization``.
        opset: ONNX opset (default: the exporter's).
        rewrite: export ENet blocks and PReLUs in their onnxruntime-friendly forms
            (:mod:`geoseg.export_rewrites`); ``False`` exports the modules as they are.

    Returns:
        The written path.
    """
    import onnx

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = prepare_for_export(model, rewrite=rewrite)
    if example_inputs is None:
        example_inputs = default_example_inputs(model)
    inputs = (
        (example_inputs,) if isinstance(example_inputs, torch.Tensor) else tuple(example_inputs)
    )
    inputs = tuple(x.detach().cpu().float() for x in inputs)
    was_training = model.training
    device = next((p.device for p in model.parameters()), torch.device("cpu"))
    model.eval().cpu()
    try:
        with torch.no_grad():
            probe = model(*inputs)
        if not isinstance(probe, Mapping):
            raise GeosegError(
                f"model: forward must return a dict of tensors, got {type(probe).__name__}"
            )
        output_names = list(probe)
        input_names = _forward_arg_names(model, len(inputs))
        attempts = [True, False] if dynamic else [None]
        program = None
        spatial_used = False
        for spatial in attempts:
            kwargs: dict[str, Any] = {}
            if spatial is not None:
                kwargs["dynamic_shapes"] = _dynamic_shapes(input_names, inputs, spatial)
            if opset is not None:
                kwargs["opset_version"] = opset
            try:
                with contextlib.redirect_stdout(io.StringIO()), _quiet_exporter_logs():
                    program = torch.onnx.export(
                        model,
                        inputs,
                        dynamo=True,
                        input_names=input_names,
                        output_names=output_names,
                        verbose=False,
                        **kwargs,
                    )
                spatial_used = bool(spatial)
                break
            except Exception as err:
                if spatial:
                    logger.warning(
                        "%s: dynamic image size failed (%s); exporting with a dynamic batch only",
                        type(model).__name__,
                        str(err).splitlines()[0][:200],
                    )
                    continue
                raise GeosegError(
                    f"{path}: ONNX export of {type(model).__name__} failed: {err}"
                ) from err
    finally:
        model.train(was_training).to(device)
    proto = program.model_proto
    meta = {"outputs": output_names, "inputs": input_names, "dynamic_spatial": spatial_used}
    meta.update(metadata or {})
    for key, value in meta.items():
        entry = proto.metadata_props.add()
        entry.key = META_PREFIX + key
        entry.value = value if isinstance(value, str) else json.dumps(value)
    entry = proto.metadata_props.add()
    entry.key = META_PREFIX + DIGEST_PROP
    entry.value = onnx_content_sha256(proto)
    atomic_write(path, proto.SerializeToString())
    onnx.checker.check_model(str(path))
    logger.info("exported %s to %s", type(model).__name__, path)
    return path


def available_providers(device: str | None = None) -> list[str]:
    """onnxruntime providers for ``device`` (``"cuda"``, ``"cpu"`` or ``None`` = best available)."""
    import onnxruntime as ort

    have = ort.get_available_providers()
    if device == "cpu":
        return ["CPUExecutionProvider"]
    wanted = ["CUDAExecutionProvider", "CPUExecutionProvider"]
    chosen = [p for p in wanted if p in have]
    if device == "cuda" and "CUDAExecutionProvider" not in chosen:
        raise GeosegError("device: CUDA requested but onnxruntime has no CUDAExecutionProvider")
    return chosen


def check_providers(providers: Sequence[str] | None) -> list[str]:
    """``providers`` checked against onnxruntime's (default: :func:`available_providers`).

    Raises:
        GeosegError: an empty list, a name onnxruntime does not know, or one this installation
            does not have (onnxruntime would silently fall back to the CPU).
    """
    import onnxruntime as ort

    if providers is None:
        return available_providers()
    if isinstance(providers, str):
        providers = [providers]
    chosen = list(providers)
    if not chosen:
        raise GeosegError("providers: expected at least one onnxruntime execution provider")
    known, have = set(ort.get_all_providers()), ort.get_available_providers()
    for name in chosen:
        if name not in known:
            raise GeosegError(
                f"providers: unknown onnxruntime execution provider {name!r}; available here: "
                f"{have}"
            )
        if name not in have:
            raise GeosegError(
                f"providers: {name} is not available in this onnxruntime installation "
                f"(available: {have})"
            )
    return chosen


class OnnxModel:
    """An onnxruntime session with the torch model's call signature and named outputs.

    Args:
        path: ``.onnx`` file written by :func:`export_onnx` (or any ONNX model).
        providers: onnxruntime execution providers (default: CUDA when available, then CPU).
        threads: intra-op threads (``None``: onnxruntime's default). The worker threads stop
            spinning when a call returns (``session.force_spinning_stop``): sessions called in
            turn, as a pipeline calls the joint network and then the relocalisation heads,
            otherwise compete with each other's spinning threads (two sessions alternating on
            this project's 2-core CPU: ~90 ms per joint-network call instead of ~56 ms).
        fixed_dims: symbolic input dimensions to fix for this session, e.g. ``{"batch": 1,
            "height": 480, "width": 640}`` (the names :func:`export_onnx` gives; the file is
            unchanged). onnxruntime then resolves every tensor's shape when it builds the session:
            the joint network at 640x480 runs in ~0.85x the time of the same file's dynamic
            session on this project's CPU (its convolutions ~20 % faster, memory planned once).
            Inputs of another size are rejected (:class:`GeosegError`).
            ``"auto"``: every input shape gets its own fixed session on first use (~0.2 s to
            build for the joint network), up to :attr:`MAX_FIXED_SESSIONS` shapes; further
            shapes run on the dynamic session.

    Raises:
        GeosegError: missing, corrupt or invalid file (the message names the file).

    Call:
        ``model(x)`` or ``model(a, b)`` with NumPy arrays or torch tensors, e.g. `(B, 3, H, W)`
        float images; returns ``{output name: array}`` (tensors when the inputs were tensors).
    """

    MAX_FIXED_SESSIONS = 4

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        providers: Sequence[str] | None = None,
        threads: int | None = None,
        fixed_dims: Mapping[str, int] | str | None = None,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise GeosegError(f"{self.path}: no such ONNX file")
        verify_onnx_file(self.path)
        if isinstance(fixed_dims, str) and fixed_dims != "auto":
            raise GeosegError(f"fixed_dims: expected a mapping, 'auto' or None, got {fixed_dims!r}")
        self._auto = fixed_dims == "auto"
        self._providers = check_providers(providers)
        if threads is not None and (
            isinstance(threads, bool) or not isinstance(threads, int | np.integer) or threads < 1
        ):
            raise GeosegError(f"threads: expected None or an int >= 1, got {threads!r}")
        self._threads = threads
        self.session = self._new_session(None if self._auto else fixed_dims)
        raw = self.session.get_modelmeta().custom_metadata_map
        self.metadata: dict[str, Any] = {}
        for key, value in raw.items():
            if key.startswith(META_PREFIX):
                try:
                    self.metadata[key[len(META_PREFIX) :]] = json.loads(value)
                except json.JSONDecodeError:
                    self.metadata[key[len(META_PREFIX) :]] = value
        self._inputs = self.session.get_inputs()
        # per input, the symbolic dimension names by axis (for "auto")
        self._symbolic = [
            {axis: d for axis, d in enumerate(i.shape) if isinstance(d, str)} for i in self._inputs
        ]
        self._fixed_sessions: dict[tuple, Any] = {}
        if fixed_dims and not self._auto:
            declared = self._declared_dims()
            unknown = sorted(set(fixed_dims) - declared)
            if unknown:
                raise GeosegError(
                    f"{self.path}: fixed_dims {unknown} are not symbolic input dimensions "
                    f"(the file has {sorted(declared) or 'none'})"
                )
        self.input_names = [i.name for i in self._inputs]
        self.output_names = [o.name for o in self.session.get_outputs()]

    def _new_session(self, fixed_dims: Mapping[str, int] | None):
        import onnxruntime as ort

        options = ort.SessionOptions()
        if self._threads is not None:
            options.intra_op_num_threads = self._threads
        options.add_session_config_entry("session.force_spinning_stop", "1")
        for name, size in (fixed_dims or {}).items():
            if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
                raise GeosegError(f"fixed_dims[{name!r}]: expected a positive int, got {size!r}")
            options.add_free_dimension_override_by_name(name, int(size))
        try:
            session = ort.InferenceSession(
                str(self.path), sess_options=options, providers=self._providers
            )
        except Exception as err:
            raise GeosegError(f"{self.path}: not a valid ONNX model ({err})") from None
        used = session.get_providers()
        if self._providers[0] not in used:  # onnxruntime fell back silently
            raise GeosegError(
                f"{self.path}: onnxruntime could not use {self._providers[0]} (the session runs "
                f"on {used}); fix its installation or ask for another provider"
            )
        return session

    def _session_for(self, shapes: tuple[tuple[int, ...], ...]):
        """With ``fixed_dims="auto"``: the session fixed to these input shapes (built on first
        use, while fewer than :attr:`MAX_FIXED_SESSIONS` exist), else the dynamic one."""
        if not self._auto or not any(self._symbolic):
            return self.session
        session = self._fixed_sessions.get(shapes)
        if session is None and len(self._fixed_sessions) < self.MAX_FIXED_SESSIONS:
            dims: dict[str, int] = {}
            for names, shape in zip(self._symbolic, shapes):
                for axis, name in names.items():
                    if dims.setdefault(name, shape[axis]) != shape[axis]:
                        return self.session  # one name, two sizes: onnxruntime decides
            session = self._fixed_sessions[shapes] = self._new_session(dims)
            logger.debug("%s: session fixed to %s", self.path, dims)
        return self.session if session is None else session

    def _declared_dims(self) -> set[str]:
        """The symbolic dimension names of the file's inputs (before any ``fixed_dims``)."""
        import onnx

        graph = onnx.load(str(self.path), load_external_data=False).graph
        initializers = {t.name for t in graph.initializer}
        return {
            d.dim_param
            for i in graph.input
            if i.name not in initializers
            for d in i.type.tensor_type.shape.dim
            if d.dim_param
        }

    @property
    def providers(self) -> list[str]:
        """The providers the session actually uses."""
        return self.session.get_providers()

    def __repr__(self) -> str:
        return f"OnnxModel({str(self.path)!r}, outputs={self.output_names})"

    def _check(self, name: str, arr: np.ndarray, spec) -> np.ndarray:
        shape = spec.shape
        if arr.ndim != len(shape):
            raise GeosegError(
                f"{self.path}: input {name!r} expects {len(shape)}-D {tuple(shape)}, got shape {arr.shape}"
            )
        for i, (want, got) in enumerate(zip(shape, arr.shape)):
            if isinstance(want, int) and want != got:
                raise GeosegError(
                    f"{self.path}: input {name!r} expects size {want} in dim {i} "
                    f"({tuple(shape)}), got shape {arr.shape}"
                )
        if not np.issubdtype(arr.dtype, np.floating):
            raise GeosegError(f"{self.path}: input {name!r} expects float32, got dtype {arr.dtype}")
        if not np.isfinite(arr).all():
            raise GeosegError(f"{self.path}: input {name!r} contains NaN or infinite values")
        return np.ascontiguousarray(arr, dtype=np.float32)

    def __call__(self, *inputs: np.ndarray | torch.Tensor) -> dict[str, Any]:
        if len(inputs) != len(self._inputs):
            raise GeosegError(
                f"{self.path}: expected {len(self._inputs)} input(s) {self.input_names}, got {len(inputs)}"
            )
        as_torch = any(isinstance(x, torch.Tensor) for x in inputs)
        feed = {}
        for spec, x in zip(self._inputs, inputs):
            arr = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
            feed[spec.name] = self._check(spec.name, arr, spec)
        session = self._session_for(tuple(feed[i.name].shape for i in self._inputs))
        try:
            outs = session.run(None, feed)
        except Exception as err:
            raise GeosegError(f"{self.path}: onnxruntime failed ({err})") from None
        result = dict(zip(self.output_names, outs))
        if as_torch:
            return {k: torch.from_numpy(v) for k, v in result.items()}
        return result

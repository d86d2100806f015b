"""Export an F-PN cascade (torch) as an ONNX victim directory: one fixed-shape graph per stage.

Stages and graph batch sizes (the runtime pads partial batches):

* ``detector_2d`` — the YOLO network, letterboxed image (B2, 3, H_in, W_in) -> raw head tensors
  ``head_i`` (B2, A·(5 + C), H_i, W_i); B2 = ``batch_2d`` (default 1: the harness letterboxes
  and detects image by image).
* ``instance_segmentation`` — points (Bs, N, 4) + one_hot (Bs, 3) -> seg_logits (Bs, N, 2);
  Bs = ``batch_seg`` (default 4, the cascade's frustum batch).
* ``center_regression`` (T-Net) and ``box_estimation`` — object_points (1, M, 3) + one_hot (1, 3)
  -> center_delta (1, 3) / box_output (1, 59). Batch 1 by design: fully connected layers give
  results that depend in the last bits on a row's position in a batched product, so both
  backends run these per frustum and a box never depends on its batch.

The exporter is explicit: ``"dynamo"`` (``torch.onnx.export(dynamo=True)``, needs onnxscript) or
``"legacy"`` (the TorchScript exporter, ``dynamo=False``; deprecated, present in torch 2.13).
Shapes are fixed: no dynamic axes, so nothing is specialised or guarded.

Byte-determinism: doc strings and metadata properties (the dynamo exporter stores source paths
and stack traces there) are removed, and the protobuf is serialised deterministically, so the
same weights, exporter, opset and library versions give the same sha256 on any machine.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import io
import logging
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch
from torch import nn

from robustbench3d import __version__
from robustbench3d.errors import RobustBenchError
from robustbench3d.fileio import atomic_write_bytes, atomic_write_text
from robustbench3d.victims.cascade import FPointNetCascade
from robustbench3d.victims.onnx import MANIFEST_FILE
from robustbench3d.victims.onnx.manifest import (
    BOX,
    CENTER,
    DETECTOR_2D,
    FPN_IO,
    IMAGE_INPUT,
    SEGMENTATION,
    Manifest,
    StageSpec,
    TensorSpec,
    check_layout,
    head_name,
    read_manifest,
    verify_files,
)
from robustbench3d.victims.onnx.options import DEFAULT_OPSET, EXPORTERS, ExportOptions

#: Batch size of the T-Net and box graphs (see the module docstring).
PER_FRUSTUM_BATCH = 1


class ExportError(RobustBenchError):
    """The exporter failed or produced a graph that is not plain ONNX."""


@dataclass(frozen=True)
class StageModule:
    """A torch module to export as one stage, with example inputs and tensor names."""

    name: str
    module: nn.Module
    inputs: tuple[torch.Tensor, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]


def stage_modules(cascade: FPointNetCascade, options: ExportOptions) -> list[StageModule]:
    """The four stages of ``cascade`` with seeded example inputs of the graph shapes."""
    gen = torch.Generator().manual_seed(0)
    w_in, h_in = cascade.yolo.cfg.input_size
    fcfg = cascade.fpn.cfg
    n, m, k = fcfg.num_points, fcfg.num_object_points, fcfg.one_hot_dim

    def one_hot(b: int) -> torch.Tensor:
        return nn.functional.one_hot(torch.arange(b) % k, k).float()

    heads = tuple(head_name(i) for i in range(len(cascade.yolo.net.head_strides)))
    b, p = options.batch_seg, PER_FRUSTUM_BATCH
    return [
        StageModule(DETECTOR_2D, cascade.yolo.net.eval(), (torch.rand(options.batch_2d, 3, h_in, w_in, generator=gen),),
                    (IMAGE_INPUT,), heads),
        StageModule(SEGMENTATION, cascade.fpn.seg.eval(), (torch.randn(b, n, 4, generator=gen), one_hot(b)),
                    *FPN_IO[SEGMENTATION]),
        StageModule(CENTER, cascade.fpn.tnet.eval(), (torch.randn(p, m, 3, generator=gen), one_hot(p)),
                    *FPN_IO[CENTER]),
        StageModule(BOX, cascade.fpn.box.eval(), (torch.randn(p, m, 3, generator=gen), one_hot(p)), *FPN_IO[BOX]),
    ]


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence the exporters' progress prints, log lines and deprecation warnings; a TracerWarning
    (a Python branch frozen at trace time) becomes an error."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "torch._export", "onnxscript")]
    levels = [lg.level for lg in loggers]
    try:
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore", DeprecationWarning)
            warnings.simplefilter("ignore", FutureWarning)
            warnings.simplefilter("ignore", UserWarning)
            warnings.simplefilter("error", torch.jit.TracerWarning)
            yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def export_proto(stage: StageModule, exporter: str, opset: int) -> onnx.ModelProto:
    """Export one stage with the chosen exporter (fixed shapes) and return the ModelProto."""
    kwargs: dict[str, Any] = {"input_names": list(stage.input_names), "output_names": list(stage.output_names),
                              "opset_version": opset}
    try:
        with _quiet_exporter(), torch.inference_mode(False), torch.no_grad():
            if exporter == "dynamo":
                program = torch.onnx.export(stage.module, stage.inputs, dynamo=True, verbose=False, **kwargs)
                if program is None:
                    raise ExportError(f"stage {stage.name!r}: the dynamo exporter returned no program")
                return program.model_proto
            buffer = io.BytesIO()
            torch.onnx.export(stage.module, stage.inputs, buffer, dynamo=False, do_constant_folding=True, **kwargs)
            return onnx.load_from_string(buffer.getvalue())
    except ExportError:
        raise
    except Exception as exc:
        raise ExportError(f"stage {stage.name!r}: {exporter} export failed: {type(exc).__name__}: {exc}") from exc


def _strip(message: Any) -> None:
    """Remove doc strings and metadata properties from a protobuf message tree (in place)."""
    for field, value in message.ListFields():
        if field.name in ("doc_string", "metadata_props"):
            message.ClearField(field.name)
        elif field.type == field.TYPE_MESSAGE:
            repeated = field.is_repeated if hasattr(field, "is_repeated") else field.label == field.LABEL_REPEATED
            for item in value if repeated else (value,):
                if hasattr(item, "ListFields"):
                    _strip(item)


def canonical_bytes(proto: onnx.ModelProto, stage: str) -> bytes:
    """Checked, metadata-free, deterministically serialised model bytes."""
    _strip(proto)
    bad = sorted({f"{n.domain}::{n.op_type}" for n in proto.graph.node if n.domain not in ("", "ai.onnx")})
    if bad:
        raise ExportError(f"stage {stage!r}: exported graph uses non-standard ops {', '.join(bad)} "
                          "(onnxruntime's CPU provider may not run them)")
    try:
        onnx.checker.check_model(proto, full_check=True)
    except onnx.checker.ValidationError as exc:
        raise ExportError(f"stage {stage!r}: exported graph fails the ONNX checker: {exc}") from exc
    return proto.SerializeToString(deterministic=True)


def graph_io(proto: onnx.ModelProto, stage: str) -> tuple[tuple[TensorSpec, ...], tuple[TensorSpec, ...]]:
    """Inputs and outputs of a graph; every dimension must be fixed and every tensor float32."""
    def spec(value: onnx.ValueInfoProto) -> TensorSpec:
        t = value.type.tensor_type
        if t.elem_type != onnx.TensorProto.FLOAT:
            raise ExportError(f"stage {stage!r}: tensor {value.name!r} is not float32")
        dims = [d.dim_value if d.HasField("dim_value") else 0 for d in t.shape.dim]
        if not all(d > 0 for d in dims):
            raise ExportError(f"stage {stage!r}: tensor {value.name!r} has a symbolic dimension")
        return TensorSpec(value.name, tuple(dims))

    initializers = {i.name for i in proto.graph.initializer}
    inputs = tuple(spec(v) for v in proto.graph.input if v.name not in initializers)
    return inputs, tuple(spec(v) for v in proto.graph.output)


def exporter_record(options: ExportOptions) -> dict[str, Any]:
    """Exporter name, call, opset and library versions (what the stage bytes depend on)."""
    def version(dist: str) -> str | None:
        try:
            return importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            return None

    call = "torch.onnx.export(dynamo=True)" if options.exporter == "dynamo" else "torch.onnx.export(dynamo=False)"
    return {"name": options.exporter, "call": call, "opset": options.opset, "torch": torch.__version__,
            "onnx": onnx.__version__, "onnxscript": version("onnxscript") if options.exporter == "dynamo" else None}


def shared_stage_files(out: Path, share: str | Path | None) -> dict[str, str]:
    """sha256 -> ``../SIBLING/NAME.onnx`` of the verified stage files of ``share``, an ONNX victim
    directory beside ``out`` (empty without ``share``)."""
    if share is None:
        return {}
    share = Path(share).resolve()  # also DIR/../SIBLING before DIR exists (the recorded reproduce command)
    if share.parent != out.resolve().parent or share == out.resolve():
        raise RobustBenchError(f"--share {share}: must be another ONNX victim directory beside {out}")
    manifest = read_manifest(share)
    verify_files(share, manifest)
    return {st.sha256: f"../{share.name}/{st.file}" for st in manifest.stages if "/" not in st.file}


def export_cascade(cascade: FPointNetCascade, out: str | Path, options: ExportOptions, *,
                   source: dict[str, Any], reproduce_command: str, share: str | Path | None = None) -> Manifest:
    """Write the four stage graphs and ``manifest.json`` (last) into ``out``.

    An old manifest is removed first, so an interrupted export never leaves a directory that
    passes as complete. ``source`` describes what was exported (victim name and arguments);
    ``reproduce_command`` is the command line that rebuilds this directory. A stage whose graph is
    byte-identical to a stage file of ``share`` (an ONNX victim directory beside ``out``) is not
    written: the manifest names that file (``../SIBLING/NAME.onnx``, pinned by its sha256).
    """
    out = Path(out)
    shared = shared_stage_files(out, share)  # a refused --share leaves ``out`` untouched
    out.mkdir(parents=True, exist_ok=True)
    (out / MANIFEST_FILE).unlink(missing_ok=True)
    stages: list[StageSpec] = []
    for stage in stage_modules(cascade, options):
        proto = export_proto(stage, options.exporter, options.opset)
        inputs, outputs = graph_io(proto, stage.name)
        data = canonical_bytes(proto, stage.name)
        sha, file = hashlib.sha256(data).hexdigest(), f"{stage.name}.onnx"
        if sha in shared:
            (out / file).unlink(missing_ok=True)
            file = shared[sha]
        else:
            atomic_write_bytes(out / file, data)
        stages.append(StageSpec(stage.name, file, sha, inputs, outputs))
    manifest = Manifest(
        stages=tuple(stages), exporter=exporter_record(options),
        config={"yolo": _jsonable(cascade.yolo.cfg.to_dict()), "fpointnet": _jsonable(cascade.fpn.cfg.to_dict()),
                "settings": cascade.settings.to_dict()},
        source=source, package_version=__version__,
        reproduce={"command": reproduce_command, "byte_deterministic": True,
                   "note": "Stage files are byte-deterministic for the torch, onnx and onnxscript versions recorded "
                           "under 'exporter': re-running the command with those versions and the same weights "
                           "reproduces every sha256. Other versions may serialise the same model differently; "
                           "check such an export with `robustbench3d parity`."})
    check_layout(manifest, out / MANIFEST_FILE)
    atomic_write_text(out / MANIFEST_FILE, manifest.to_json())
    return manifest


def _jsonable(value: Any) -> Any:
    """Tuples -> lists, numpy scalars -> Python numbers (for the manifest's config)."""
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def legacy_exporter_available() -> bool:
    """True if this torch still has the TorchScript exporter (``dynamo=False``)."""
    try:
        export_proto(StageModule("probe", nn.Linear(2, 2).eval(), (torch.zeros(2, 2),), ("x",), ("y",)), "legacy",
                     DEFAULT_OPSET)
    except ExportError:
        return False
    return True


def describe_kwargs(kwargs: dict[str, Any]) -> dict[str, Any]:
    """Factory arguments for the manifest: existing files by name and sha256 (no local paths)."""
    from robustbench3d.fileio import sha256_file

    out: dict[str, Any] = {}
    for key, value in sorted(kwargs.items()):
        if isinstance(value, str | Path) and Path(value).is_file():
            out[key] = {"file": Path(value).name, "sha256": sha256_file(value)}
        else:
            out[key] = value
    return out


__all__ = [
    "DEFAULT_OPSET", "EXPORTERS", "PER_FRUSTUM_BATCH", "ExportError", "ExportOptions", "StageModule",
    "canonical_bytes", "describe_kwargs", "export_cascade", "export_proto", "exporter_record",
    "legacy_exporter_available", "stage_modules",
]

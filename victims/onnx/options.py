"""How an F-PN cascade is exported (:class:`ExportOptions`): the exporter, the opset and the 2D and segmentation
graphs' fixed batches, with their defaults and ranges.

Standard library only: ``victims export-onnx --help`` shows them without torch, and both the command
(:mod:`robustbench3d.commands.victims_export_onnx`) and the exporter (:mod:`robustbench3d.victims.onnx.export`)
take them from here.
"""

from __future__ import annotations

from dataclasses import dataclass

#: The exporters: ``torch.onnx.export(dynamo=True)`` (needs onnxscript) or the TorchScript one (``dynamo=False``).
EXPORTERS: tuple[str, ...] = ("dynamo", "legacy")
#: Default opset: the lowest the dynamo exporter builds, also supported by the legacy one.
DEFAULT_OPSET = 18
#: Default fixed batch of the 2D graph (the harness letterboxes and detects image by image).
DEFAULT_BATCH_2D = 1
#: Default fixed batch of the segmentation graph (the cascade's frustum batch).
DEFAULT_BATCH_SEG = 4
#: ``--opset`` range: 18 is the lowest opset the dynamo exporter builds, 23 the highest the supported
#: torch (2.13) exporters write; onnxruntime runs both.
OPSET_RANGE = (18, 23)
#: ``--batch-2d`` range: the 2D graph's fixed batch of letterboxed frame images. Partial batches are
#: zero-padded, so a batch larger than the frames a run evaluates together only wastes time and memory.
BATCH_2D_RANGE = (1, 64)
#: ``--batch-seg`` range: the segmentation graph's fixed batch of frustums (zero-padded likewise; a frame
#: has a few dozen proposals). The full config holds 1024 x 1603 float32 per-point features per frustum
#: (6.6 MB), so 256 frustums already take 1.7 GB.
BATCH_SEG_RANGE = (1, 256)


@dataclass(frozen=True)
class ExportOptions:
    """How to export: exporter ("dynamo" | "legacy"), opset, 2D and segmentation graph batches."""

    exporter: str
    opset: int = DEFAULT_OPSET
    batch_2d: int = DEFAULT_BATCH_2D
    batch_seg: int = DEFAULT_BATCH_SEG

    def __post_init__(self) -> None:
        if self.exporter not in EXPORTERS:
            raise ValueError(f"exporter must be one of {EXPORTERS}, got {self.exporter!r}")
        for what, value, (lo, hi) in (("opset", self.opset, OPSET_RANGE), ("batch_2d", self.batch_2d, BATCH_2D_RANGE),
                                      ("batch_seg", self.batch_seg, BATCH_SEG_RANGE)):
            if not lo <= value <= hi:
                raise ValueError(f"{what} must be an integer in [{lo}, {hi}], got {value}")


__all__ = [
    "BATCH_2D_RANGE", "BATCH_SEG_RANGE", "DEFAULT_BATCH_2D", "DEFAULT_BATCH_SEG", "DEFAULT_OPSET", "EXPORTERS",
    "OPSET_RANGE", "ExportOptions",
]

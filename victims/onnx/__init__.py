"""ONNX victims: the F-PN cascade as four fixed-shape ONNX graphs run by onnxruntime.

A victim directory holds ``manifest.json`` (:mod:`.manifest`) and one ``.onnx`` file per stage:
the 2D detector, instance segmentation, T-Net (centre regression) and box estimation. The glue
between them (letterbox, 2D decoding and NMS, frustum extraction, masking, gather, box decoding)
is the numpy code the torch victim runs too (:mod:`robustbench3d.victims.fpointnet.pipeline`).

* :mod:`.export` — torch -> ONNX, one graph per stage, byte-deterministic (needs torch).
* :mod:`.options` — :class:`~.options.ExportOptions`: exporter, opset and graph batches with their defaults
  and ranges (standard library only; shared by ``victims export-onnx`` and the exporter).
* :mod:`.runtime` — :class:`~.runtime.OnnxCascade`, the victim (onnxruntime + numpy only).
* :mod:`.registration` — ``victims add-onnx`` (a registry file in the cache) and directories given
  directly to ``run --victims`` (standard library only).
* :mod:`.parity` — torch vs onnxruntime at three levels: stage tensors, boxes per frame, AP.

Importing this package imports only the standard library.
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: The manifest file of an ONNX victim directory.
MANIFEST_FILE = "manifest.json"


def require(module: str) -> ModuleType:
    """Import an optional dependency of the ONNX victims, or raise a clear error saying how to get it."""
    from robustbench3d.errors import RobustBenchError

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise RobustBenchError(f"{module} is needed for ONNX victims but cannot be imported ({exc}); install "
                               "the extra: pip install 'robustbench3d[onnx]' (with the project's constraints "
                               "file)") from None

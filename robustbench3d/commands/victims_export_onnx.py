"""``robustbench3d victims export-onnx VICTIM --out DIR --exporter dynamo|legacy``: write an ONNX victim.

Standard library only at module level (torch and onnx load inside :func:`run`).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from robustbench3d.victims.onnx.options import (
    BATCH_2D_RANGE,
    BATCH_SEG_RANGE,
    DEFAULT_BATCH_2D,
    DEFAULT_BATCH_SEG,
    DEFAULT_OPSET,
    OPSET_RANGE,
)
from robustbench3d.victims.onnx.torch_source import add_victim_arguments, check_int_option, create_cascade


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_victim_arguments(parser)
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory (manifest.json + 4 .onnx files)")
    parser.add_argument("--exporter", required=True, choices=("dynamo", "legacy"),
                        help="torch.onnx.export(dynamo=True) (needs onnxscript) or the deprecated TorchScript "
                             "exporter (dynamo=False)")
    parser.add_argument("--share", metavar="DIR",
                        help="an ONNX victim directory beside --out: stages byte-identical to one of its stage files "
                             "are not written, the manifest names that file (two cascades with one 2D stage)")
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                        help=f"ONNX opset, {OPSET_RANGE[0]} to {OPSET_RANGE[1]} (default {DEFAULT_OPSET})")
    parser.add_argument("--batch-2d", type=int, default=DEFAULT_BATCH_2D, metavar="B",
                        help=f"fixed batch of the 2D detector graph, {BATCH_2D_RANGE[0]} to {BATCH_2D_RANGE[1]} "
                             f"(default {DEFAULT_BATCH_2D})")
    parser.add_argument("--batch-seg", type=int, default=DEFAULT_BATCH_SEG, metavar="B",
                        help=f"fixed batch of the segmentation graph, {BATCH_SEG_RANGE[0]} to {BATCH_SEG_RANGE[1]} "
                             f"(default {DEFAULT_BATCH_SEG}); the T-Net and box graphs always take one frustum")


def reproduce_command(args: argparse.Namespace, kwargs: dict[str, Any]) -> str:
    """The command line that rebuilds the export (file arguments by file name, output as DIR)."""
    from pathlib import Path

    # the spelling the shipped manifests record (a hidden alias of `victims export-onnx`): re-exports stay byte-equal
    parts = ["robustbench3d", "export-onnx", args.victim, "--out", "DIR", "--exporter", args.exporter,
             "--opset", str(args.opset), "--batch-2d", str(args.batch_2d), "--batch-seg", str(args.batch_seg)]
    if args.share:
        parts += ["--share", f"DIR/../{Path(args.share).resolve().name}"]
    for key, value in sorted(kwargs.items()):
        shown = Path(value).name if isinstance(value, str) and Path(value).is_file() else json.dumps(value)
        parts += ["--victim-arg", f"{key}={shown}"]
    return " ".join(parts)


def run(args: argparse.Namespace) -> int:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import check_output_dir
    from robustbench3d.registry import parse_kwargs
    from robustbench3d.victims.onnx import require

    check_int_option("--opset", args.opset, *OPSET_RANGE)
    check_int_option("--batch-2d", args.batch_2d, *BATCH_2D_RANGE)
    check_int_option("--batch-seg", args.batch_seg, *BATCH_SEG_RANGE)
    check_output_dir(args.out, "--out")
    require("onnx")
    if args.exporter == "dynamo":
        require("onnxscript")
    from robustbench3d.victims.onnx.export import (
        ExportOptions,
        describe_kwargs,
        export_cascade,
        legacy_exporter_available,
    )

    kwargs = parse_kwargs(args.victim_arg, "--victim-arg")
    if args.exporter == "legacy" and not legacy_exporter_available():
        raise RobustBenchError("this torch has no legacy (TorchScript) ONNX exporter; use --exporter dynamo")
    try:
        options = ExportOptions(args.exporter, args.opset, args.batch_2d, args.batch_seg)
    except ValueError as exc:
        raise RobustBenchError(str(exc)) from None
    from robustbench3d.victims import VICTIMS

    cascade = create_cascade(args.victim, kwargs, pointpillars=True)
    source: dict[str, Any] = {"victim": args.victim, "kwargs": describe_kwargs(kwargs)}
    if not any(kwargs.get(k) for k in ("weights", "yolo_weights", "fpointnet_weights", "allow_untrained")):
        # no weights given: the victim loaded its shipped file
        source["weights_sha256"] = VICTIMS.get(args.victim).info.weights_sha256
    if type(cascade).__name__ == "PointPillarsDetector":  # one graph (victims/onnx/pointpillars_export.py)
        from robustbench3d.victims.onnx.pointpillars_export import export_pointpillars

        if args.share:
            raise RobustBenchError("--share: a PointPillars export is one graph; there is no stage to share")
        path = export_pointpillars(cascade, args.out, options, source=source,
                                   reproduce_command=reproduce_command(args, kwargs))
        print(f"{path}: exporter {options.exporter} opset {options.opset}")
        return 0
    manifest = export_cascade(cascade, args.out, options, source=source,
                              reproduce_command=reproduce_command(args, kwargs), share=args.share)
    for st in manifest.stages:
        shapes = ", ".join(f"{t.name} {'x'.join(map(str, t.shape))}" for t in st.inputs)
        print(f"{st.name:<22} {st.file:<44} sha256 {st.sha256[:16]}…  {shapes}")
    ex = manifest.exporter
    print(f"{args.out}: exporter {ex['name']} opset {ex['opset']}, torch {ex['torch']}, onnx {ex['onnx']}"
          f"{', onnxscript ' + ex['onnxscript'] if ex['onnxscript'] else ''}")
    return 0

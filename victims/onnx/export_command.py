"""``robustbench3d export-onnx VICTIM --out DIR --exporter dynamo|legacy``: write an ONNX victim.

Standard library only at module level (torch and onnx load inside :func:`run`).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

#: Defaults shared with :mod:`robustbench3d.victims.onnx.export` (kept here so ``--help`` needs no torch).
DEFAULT_OPSET = 18
DEFAULT_BATCH_2D = 1
DEFAULT_BATCH_SEG = 4


def parse_kwargs(items: list[str] | None) -> dict[str, Any]:
    """``["KEY=VALUE", ...]`` -> kwargs; VALUE is parsed as JSON when it is valid JSON, else kept
    as a string (paths)."""
    from robustbench3d.errors import RobustBenchError

    out: dict[str, Any] = {}
    for item in items or []:
        key, eq, raw = item.partition("=")
        if not eq or not key.strip():
            raise RobustBenchError(f"--victim-arg {item!r}: expected KEY=VALUE (e.g. weights=cascade.pt)")
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out


def add_victim_arguments(parser: argparse.ArgumentParser) -> None:
    """VICTIM and --victim-arg (shared by export-onnx and parity)."""
    parser.add_argument("victim", metavar="VICTIM", help="registered torch victim (an F-PN cascade, e.g. fpointnet-v1)")
    parser.add_argument("--victim-arg", action="append", metavar="KEY=VALUE",
                        help="keyword argument of the victim's factory, e.g. weights=cascade.pt or "
                             "allow_untrained=true (repeatable; VALUE is JSON or a string)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_victim_arguments(parser)
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory (manifest.json + 4 .onnx files)")
    parser.add_argument("--exporter", required=True, choices=("dynamo", "legacy"),
                        help="torch.onnx.export(dynamo=True) (needs onnxscript) or the deprecated TorchScript "
                             "exporter (dynamo=False)")
    parser.add_argument("--share", metavar="DIR",
                        help="an ONNX victim directory beside --out: stages byte-identical to one of its stage files "
                             "are not written, the manifest names that file (two cascades with one 2D stage)")
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET, help=f"ONNX opset (default {DEFAULT_OPSET})")
    parser.add_argument("--batch-2d", type=int, default=DEFAULT_BATCH_2D, metavar="B",
                        help=f"fixed batch of the 2D detector graph (default {DEFAULT_BATCH_2D})")
    parser.add_argument("--batch-seg", type=int, default=DEFAULT_BATCH_SEG, metavar="B",
                        help=f"fixed batch of the segmentation graph (default {DEFAULT_BATCH_SEG}); the T-Net and "
                             "box graphs always take one frustum")


def reproduce_command(args: argparse.Namespace, kwargs: dict[str, Any]) -> str:
    """The command line that rebuilds the export (file arguments by file name, output as DIR)."""
    from pathlib import Path

    parts = ["robustbench3d", "export-onnx", args.victim, "--out", "DIR", "--exporter", args.exporter,
             "--opset", str(args.opset), "--batch-2d", str(args.batch_2d), "--batch-seg", str(args.batch_seg)]
    if args.share:
        parts += ["--share", f"DIR/../{Path(args.share).resolve().name}"]
    for key, value in sorted(kwargs.items()):
        shown = Path(value).name if isinstance(value, str) and Path(value).is_file() else json.dumps(value)
        parts += ["--victim-arg", f"{key}={shown}"]
    return " ".join(parts)


def create_cascade(name: str, kwargs: dict[str, Any]) -> Any:
    """The registered victim ``name``, which must be an F-PN cascade (torch)."""
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims import create_victim
    from robustbench3d.victims.cascade import FPointNetCascade

    victim = create_victim(name, **kwargs)
    if not isinstance(victim, FPointNetCascade):
        raise RobustBenchError(f"victim {name!r} is a {type(victim).__name__}; only F-PN cascades "
                               "(FPointNetCascade) can be exported per stage")
    return victim


def run(args: argparse.Namespace) -> int:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import check_output_dir
    from robustbench3d.victims.onnx import require

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

    kwargs = parse_kwargs(args.victim_arg)
    if args.exporter == "legacy" and not legacy_exporter_available():
        raise RobustBenchError("this torch has no legacy (TorchScript) ONNX exporter; use --exporter dynamo")
    try:
        options = ExportOptions(args.exporter, args.opset, args.batch_2d, args.batch_seg)
    except ValueError as exc:
        raise RobustBenchError(str(exc)) from None
    from robustbench3d.victims import VICTIMS

    cascade = create_cascade(args.victim, kwargs)
    source: dict[str, Any] = {"victim": args.victim, "kwargs": describe_kwargs(kwargs)}
    if not any(kwargs.get(k) for k in ("weights", "yolo_weights", "fpointnet_weights", "allow_untrained")):
        # no weights given: the victim loaded its shipped file
        source["weights_sha256"] = VICTIMS.get(args.victim).info.weights_sha256
    manifest = export_cascade(cascade, args.out, options, source=source,
                              reproduce_command=reproduce_command(args, kwargs), share=args.share)
    for st in manifest.stages:
        shapes = ", ".join(f"{t.name} {'x'.join(map(str, t.shape))}" for t in st.inputs)
        print(f"{st.name:<22} {st.file:<44} sha256 {st.sha256[:16]}…  {shapes}")
    ex = manifest.exporter
    print(f"{args.out}: exporter {ex['name']} opset {ex['opset']}, torch {ex['torch']}, onnx {ex['onnx']}"
          f"{', onnxscript ' + ex['onnxscript'] if ex['onnxscript'] else ''}")
    return 0

"""``robustbench3d export-onnx VICTIM --out DIR --exporter dynamo|legacy``: write an ONNX victim.

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


def check_int_option(option: str, value: int | None, lo: int, hi: int | None = None) -> None:
    """Refuse (:class:`RobustBenchError`, naming ``option``) an integer option outside [lo, hi] (hi None:
    no upper bound); None (not given) passes."""
    from robustbench3d.errors import RobustBenchError

    if value is not None and not (lo <= value and (hi is None or value <= hi)):
        bounds = f"in [{lo}, {hi}]" if hi is not None else f">= {lo}"
        raise RobustBenchError(f"{option}: {value} is out of range (an integer {bounds})")


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

    parts = ["robustbench3d", "export-onnx", args.victim, "--out", "DIR", "--exporter", args.exporter,
             "--opset", str(args.opset), "--batch-2d", str(args.batch_2d), "--batch-seg", str(args.batch_seg)]
    if args.share:
        parts += ["--share", f"DIR/../{Path(args.share).resolve().name}"]
    for key, value in sorted(kwargs.items()):
        shown = Path(value).name if isinstance(value, str) and Path(value).is_file() else json.dumps(value)
        parts += ["--victim-arg", f"{key}={shown}"]
    return " ".join(parts)


def check_factory_kwargs(name: str, kwargs: dict[str, Any]) -> None:
    """Refuse, before the victim is built, a ``--victim-arg`` key its factory does not take (one line
    listing the keys it does take; a factory with ``**kwargs`` takes any)."""
    import inspect

    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims import VICTIMS

    try:
        params = inspect.signature(VICTIMS.get(name).factory).parameters
    except (TypeError, ValueError):  # no readable signature: the factory call says
        return
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return
    takes = [k for k, p in params.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    unknown = sorted(set(kwargs) - set(takes))
    if unknown:
        raise RobustBenchError(f"--victim-arg {unknown[0]}=...: victim {name!r} takes no argument {unknown[0]!r} "
                               f"(it takes {', '.join(takes) or 'none'})")


def create_cascade(name: str, kwargs: dict[str, Any]) -> Any:
    """The registered victim ``name``, which must be an F-PN cascade (torch)."""
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims import create_victim
    from robustbench3d.victims.cascade import FPointNetCascade

    check_factory_kwargs(name, kwargs)
    victim = create_victim(name, **kwargs)
    if not isinstance(victim, FPointNetCascade):
        raise RobustBenchError(f"victim {name!r} is a {type(victim).__name__}; only F-PN cascades "
                               "(FPointNetCascade) can be exported per stage")
    return victim


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

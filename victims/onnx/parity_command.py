"""``robustbench3d parity VICTIM [--onnx DIR] [--data DIR] [--max-frames N]``: torch vs onnxruntime.

Without ``--onnx`` the victim is exported to a temporary directory first (``--exporter``). The
ONNX victim runs with the torch victim's seed and gather mode. Exit status 0 when every level
passes, 1 otherwise. Standard library only at module level.
"""

from __future__ import annotations

import argparse
import json

from robustbench3d.victims.onnx.export_command import add_victim_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_victim_arguments(parser)
    parser.add_argument("--onnx", metavar="DIR",
                        help="ONNX victim directory (default: export VICTIM to a temporary one)")
    parser.add_argument("--exporter", default="dynamo", choices=("dynamo", "legacy"),
                        help="exporter used when --onnx is not given (default dynamo)")
    parser.add_argument("--data", metavar="DIR",
                        help="KITTI-layout dataset root (default: the embedded dataset, generated if missing)")
    parser.add_argument("--split", default="val", help="split name (default: val)")
    parser.add_argument("--max-frames", type=int, metavar="N", help="only the first N frames of the split")
    parser.add_argument("--proposals", default="gt,detector", metavar="SRC[,SRC]",
                        help="proposal sources compared at the box and AP levels (default: gt,detector)")
    parser.add_argument("--seed", type=int, default=0, help="seed= of the victim unless given by --victim-arg (0)")
    parser.add_argument("--json", metavar="PATH", help="also write the report as JSON")


def run(args: argparse.Namespace) -> int:
    import tempfile
    from pathlib import Path

    from robustbench3d.datasets import load_ground_truth, resolve_dataset
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import atomic_write_text, check_output_file
    from robustbench3d.kitti.dataset import Frame
    from robustbench3d.victims.onnx import require

    if args.json:
        check_output_file(args.json, "--json")
    require("onnx")
    require("onnxruntime")
    if not args.onnx and args.exporter == "dynamo":
        require("onnxscript")
    from robustbench3d.victims.onnx.export import ExportOptions, describe_kwargs, export_cascade
    from robustbench3d.victims.onnx.export_command import create_cascade, parse_kwargs
    from robustbench3d.victims.onnx.parity import format_report, run_parity
    from robustbench3d.victims.onnx.runtime import OnnxCascade

    proposals = [p.strip() for p in args.proposals.split(",") if p.strip()]
    bad = [p for p in proposals if p not in ("gt", "detector")]
    if bad or not proposals:
        raise RobustBenchError(f"--proposals: choose from gt, detector (got {args.proposals!r})")
    kwargs = parse_kwargs(args.victim_arg)
    kwargs.setdefault("seed", args.seed)
    victim = create_cascade(args.victim, kwargs)
    dataset = resolve_dataset(args.data, args.split)
    gt = load_ground_truth(dataset, args.max_frames)
    kitti = dataset.kitti()
    frames = [Frame(fid, kitti.image(fid), kitti.scan(fid), kitti.calib(fid), labels)
              for fid, labels in zip(gt.frame_ids, gt.labels, strict=True)]
    with tempfile.TemporaryDirectory(prefix="robustbench3d-onnx-") as tmp:
        directory = Path(args.onnx) if args.onnx else Path(tmp)
        if not args.onnx:
            export_cascade(victim, directory, ExportOptions(args.exporter),
                           source={"victim": args.victim, "kwargs": describe_kwargs(kwargs)},
                           reproduce_command="(temporary export by robustbench3d parity)")
        onnx_victim = OnnxCascade(directory, seed=victim.settings.seed, gather=victim.settings.gather)
        print(f"{args.victim} (torch) vs {directory if args.onnx else 'a temporary ' + args.exporter + ' export'} "
              f"(onnxruntime) on {len(frames)} frames of {dataset.root} split {args.split}")
        report = run_parity(victim, onnx_victim, frames, proposals=proposals)
    print(format_report(report))
    if args.json:
        atomic_write_text(args.json, json.dumps(report.to_dict(), indent=2, default=float) + "\n")
    return 0 if report.ok else 1

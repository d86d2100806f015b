"""``robustbench3d victims parity VICTIM [--onnx DIR] [--data DIR] [--max-frames N]``: torch vs onnxruntime.

Without ``--onnx`` the victim is exported to a temporary directory first (``--exporter``). The
ONNX victim runs with the torch victim's seed and gather mode. Exit status 0 when every level
passes, 1 otherwise; 2 on bad input. Checked before any work (no weights loaded, no dataset
generated): ``--onnx DIR`` (its manifest and every stage file's sha256), ``--json`` (a new file
unless ``--force``), ``--max-frames`` (>= 1), ``--seed`` (in
:data:`~robustbench3d.victims.zoo.SEED_RANGE`), ``--proposals`` and the ``--victim-arg`` form.
Standard library only at module level.
"""

from __future__ import annotations

import argparse
import json

from robustbench3d.victims.onnx.torch_source import add_victim_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_victim_arguments(parser)
    parser.add_argument("--onnx", metavar="DIR",
                        help="ONNX victim directory (default: export VICTIM to a temporary one)")
    parser.add_argument("--exporter", default="dynamo", choices=("dynamo", "legacy"),
                        help="exporter used when --onnx is not given (default dynamo)")
    parser.add_argument("--data", metavar="DIR",
                        help="KITTI-layout dataset root (default: the embedded dataset, generated if missing)")
    parser.add_argument("--split", default="val", help="split name (default: val)")
    parser.add_argument("--max-frames", type=int, metavar="N",
                        help="only the first N frames of the split (N >= 1; default: all)")
    parser.add_argument("--proposals", default="gt,detector", metavar="SRC[,SRC]",
                        help="proposal sources compared at the box and AP levels (default: gt,detector)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed= of the victim unless given by --victim-arg, 0 to 2**63-1 (default 0)")
    parser.add_argument("--json", metavar="PATH", help="also write the report as JSON (a new file unless --force)")
    parser.add_argument("--force", action="store_true", help="let --json replace an existing file")


def check_onnx_dir(directory: str) -> None:
    """``--onnx DIR``, before any work: a directory holding a valid ``manifest.json`` whose stage files
    exist with the manifest's sha256 (:class:`~robustbench3d.errors.DataFormatError` naming the file)."""
    from robustbench3d.victims.onnx.manifest import read_manifest, verify_files

    verify_files(directory, read_manifest(directory))


def _proposals(text: str) -> list[str]:
    from robustbench3d.errors import RobustBenchError

    proposals = [p.strip() for p in text.split(",") if p.strip()]
    if not proposals or any(p not in ("gt", "detector") for p in proposals):
        raise RobustBenchError(f"--proposals: choose from gt, detector (got {text!r})")
    return proposals


def run(args: argparse.Namespace) -> int:
    import tempfile
    from pathlib import Path

    from robustbench3d.datasets import load_ground_truth, resolve_dataset
    from robustbench3d.fileio import atomic_write_text, check_output_file, replacing_note
    from robustbench3d.kitti.dataset import Frame
    from robustbench3d.registry import parse_kwargs
    from robustbench3d.victims.onnx import require
    from robustbench3d.victims.onnx.torch_source import check_int_option, create_cascade
    from robustbench3d.victims.zoo import SEED_RANGE

    if args.json:
        check_output_file(args.json, "--json", force=args.force)
    if args.onnx:
        check_onnx_dir(args.onnx)
    check_int_option("--max-frames", args.max_frames, 1)
    check_int_option("--seed", args.seed, *SEED_RANGE)
    proposals = _proposals(args.proposals)
    kwargs = parse_kwargs(args.victim_arg, "--victim-arg")
    require("onnx")
    require("onnxruntime")
    if not args.onnx and args.exporter == "dynamo":
        require("onnxscript")
    from robustbench3d.victims.onnx.export import ExportOptions, describe_kwargs, export_cascade
    from robustbench3d.victims.onnx.parity import format_report, run_parity
    from robustbench3d.victims.onnx.runtime import OnnxCascade

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
        note = replacing_note(args.json)
        if note:
            print(note)
        atomic_write_text(args.json, json.dumps(report.to_dict(), indent=2, default=float) + "\n")
    return 0 if report.ok else 1

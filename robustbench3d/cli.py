"""``robustbench3d`` command line.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and ``run(args) -> int``.
Those modules import only the standard library at module level (numpy, torch, onnxruntime are
imported inside ``run``), so ``robustbench3d --help`` starts fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from robustbench3d import __version__
from robustbench3d.errors import RobustBenchError

#: name -> (module, one-line help). Nested groups use "group name".
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("robustbench3d.run_cli", "benchmark victims x attacks x proposal sources on a dataset split"),
    "data synth": ("robustbench3d.synth.cli", "generate the embedded procedural dataset in KITTI layout"),
    "data stats": ("robustbench3d.dataset_stats", "LiDAR/label statistics of KITTI-layout datasets, side by side"),
    "eval": ("robustbench3d.eval.cli", "score KITTI result files against ground-truth labels"),
    "show": ("robustbench3d.show", "draw a frame: image with 3D boxes and a bird's-eye view of the scan"),
    "report": ("robustbench3d.report.cli", "leaderboard of runs: sortable HTML page and markdown with figures"),
    "attack apply": ("robustbench3d.attack_apply", "write an attacked copy of a dataset split (KITTI layout + meshes)"),
    "attack check": ("robustbench3d.attack_check", "check an attacked dataset geometrically against its clean one"),
    "attack train": ("robustbench3d.attack_train", "optimise a universal roof object against a white-box victim"),
    "attack list": ("robustbench3d.attack_list", "list registered attacks: parameters, requirements, origin"),
    "victims list": ("robustbench3d.victims.list_command", "list registered victims and their capabilities"),
    "victims add-onnx": ("robustbench3d.victims.onnx.add_command", "register an ONNX victim directory under a name"),
    "victims remove": ("robustbench3d.victims.onnx.remove_command", "remove a victim added with victims add-onnx"),
    "victims pack": ("robustbench3d.victims.pack_command", "join trained YOLO and F-PN weights into one cascade file"),
    "train yolo": ("robustbench3d.victims.train_yolo", "train the YOLO 2D detector on a KITTI-layout dataset"),
    "train fpointnet": ("robustbench3d.victims.train_fpointnet", "train Frustum-PointNet v1 on GT-box frustums"),
    "export-onnx": ("robustbench3d.victims.onnx.export_command", "export an F-PN cascade victim as per-stage ONNX"),
    "parity": ("robustbench3d.victims.onnx.parity_command", "torch vs onnxruntime parity: tensors, boxes, AP"),
    "tradeoff": ("robustbench3d.tradeoff.cli", "speed/accuracy trade of the harness's settings: Pareto table"),
    "bench": ("robustbench3d.bench", "run speed/memory benchmarks and print a table"),
    "check": ("robustbench3d.gate", "regression gate: compare a run's AP and AP drops with a baseline"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="robustbench3d",
        description="Benchmark physical adversarial roof objects against camera+LiDAR 3D car detectors.",
    )
    parser.add_argument("--version", action="version", version=f"robustbench3d {__version__}")
    top = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    groups: dict[str, argparse._SubParsersAction] = {}
    for name, (module, help_text) in COMMANDS.items():
        parts = name.split()
        target = top
        if len(parts) == 2:
            if parts[0] not in groups:
                gp = top.add_parser(parts[0], help=f"{parts[0]} commands")
                groups[parts[0]] = gp.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=True)
            target = groups[parts[0]]
        sub = target.add_parser(parts[-1], help=help_text, description=help_text)
        sub.set_defaults(_module=module)
        importlib.import_module(module).add_arguments(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except RobustBenchError as exc:
        print(f"robustbench3d: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("robustbench3d: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

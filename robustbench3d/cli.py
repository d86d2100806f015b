"""``robustbench3d`` command line.

Each command lives in its own module of :mod:`robustbench3d.commands`, named after the command ("attack
train" -> ``commands/attack_train.py``, "victims export-onnx" -> ``commands/victims_export_onnx.py``), exposing
``add_arguments(parser)`` and ``run(args) -> int``. Those modules import only the standard library at module
level (numpy, torch, onnxruntime are imported inside ``run``), so ``robustbench3d --help`` starts fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from robustbench3d import __version__
from robustbench3d.errors import RobustBenchError

#: name -> one-line help. Nested groups use "group name".
COMMANDS: dict[str, str] = {
    "run": "benchmark victims x attacks x proposal sources on a dataset split",
    "data synth": "generate the embedded procedural dataset in KITTI layout",
    "data stats": "LiDAR/label statistics of KITTI-layout datasets, side by side",
    "eval": "score KITTI result files against ground-truth labels",
    "show": "draw a frame: image with 3D boxes and a bird's-eye view of the scan",
    "report": "leaderboard of runs: sortable HTML page and markdown with figures",
    "attack apply": "write an attacked copy of a dataset split (KITTI layout + meshes)",
    "attack check": "check an attacked dataset geometrically against its clean one",
    "attack train": "optimise a universal roof object against a white-box victim",
    "attack list": "list registered attacks: parameters, requirements, origin",
    "victims list": "list registered victims and their capabilities",
    "victims add-onnx": "register an ONNX victim directory under a name",
    "victims remove": "remove a victim added with victims add-onnx",
    "victims train-yolo": "train the YOLO 2D detector on a KITTI-layout dataset",
    "victims train-fpointnet": "train Frustum-PointNet v1 on GT-box frustums",
    "victims train-pointpillars": "train the PointPillars-style LiDAR Car detector",
    "victims pack": "join trained YOLO and F-PN weights into one cascade file",
    "victims export-onnx": "export an F-PN cascade victim as per-stage ONNX",
    "victims parity": "torch vs onnxruntime parity: tensors, boxes, AP",
    "tradeoff": "speed/accuracy trade of the harness's settings: Pareto table",
    "sweep": "dose-response sweep: objects of each size and colour freedom, trained and scored",
    "bench": "run speed/memory benchmarks and print a table",
    "check": "regression gate: compare a run's AP and AP drops with a baseline",
}

#: Earlier spellings, still accepted and not listed by ``--help``: old name -> command.
ALIASES: dict[str, str] = {
    "train yolo": "victims train-yolo",
    "train fpointnet": "victims train-fpointnet",
    "export-onnx": "victims export-onnx",
    "parity": "victims parity",
}


def command_module(name: str) -> str:
    """The module of command ``name`` ("victims export-onnx" -> ``robustbench3d.commands.victims_export_onnx``)."""
    return "robustbench3d.commands." + name.replace(" ", "_").replace("-", "_")


def _add(top: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction], name: str,
         command: str, help_text: str | None) -> None:
    """Add command ``command`` under ``name``; ``help_text`` None: hidden (an alias, absent from listings)."""
    *group, leaf = name.split()
    target = top
    if group:
        if group[0] not in groups:
            listed = {"help": f"{group[0]} commands"} if help_text is not None else {}
            gp = top.add_parser(group[0], **listed)
            groups[group[0]] = gp.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=True)
        target = groups[group[0]]
    text = COMMANDS[command]
    sub = target.add_parser(leaf, description=text, **({"help": help_text} if help_text is not None else {}))
    sub.set_defaults(_module=command_module(command))
    importlib.import_module(command_module(command)).add_arguments(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="robustbench3d",
        description="Benchmark physical adversarial roof objects against camera+LiDAR 3D car detectors.",
    )
    parser.add_argument("--version", action="version", version=f"robustbench3d {__version__}")
    top = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    groups: dict[str, argparse._SubParsersAction] = {}
    for name, help_text in COMMANDS.items():
        _add(top, groups, name, name, help_text)
    for old, name in ALIASES.items():
        _add(top, groups, old, name, None)
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

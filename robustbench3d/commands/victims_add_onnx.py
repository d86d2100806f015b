"""``robustbench3d victims add-onnx DIR [--name NAME]``: register an ONNX victim directory.

The directory is checked in full first (manifest, stage hashes, onnxruntime loads every graph with
the manifest's inputs and outputs), then recorded in the user registry file
(``<cache>/victims/onnx.json``). Without ``--name`` the name is the folder's name folded to ASCII
(see :func:`~robustbench3d.registry.sanitise_name`). Standard library only at
module level.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("directory", metavar="DIR", help="ONNX victim directory (written by `victims export-onnx`)")
    parser.add_argument("--name", help="victim name: lowercase letters, digits, '.', '_', '-' (default: the folder's "
                                       "name folded to ASCII, accents dropped)")
    parser.add_argument("--replace", action="store_true", help="re-point an existing ONNX victim name to DIR")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from robustbench3d.victims.onnx.registration import add_user_victim, name_for_directory
    from robustbench3d.victims.onnx.runtime import OnnxCascade

    name = args.name or name_for_directory(Path(args.directory).expanduser().resolve())
    OnnxCascade(args.directory)
    path = add_user_victim(name, args.directory, replace=args.replace)
    print(f"registered ONNX victim {name!r} -> {args.directory} (in {path})")
    return 0

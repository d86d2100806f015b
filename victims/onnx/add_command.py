"""``robustbench3d victims add-onnx DIR --name NAME``: register an ONNX victim directory.

The directory is checked in full first (manifest, stage hashes, onnxruntime loads every graph with
the manifest's inputs and outputs), then recorded in the user registry file
(``<cache>/victims/onnx.json``). Standard library only at module level.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("directory", metavar="DIR", help="ONNX victim directory (written by export-onnx)")
    parser.add_argument("--name", required=True, help="victim name (lowercase letters, digits, '.', '_', '-')")
    parser.add_argument("--replace", action="store_true", help="re-point an existing ONNX victim name to DIR")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.victims.onnx.registration import add_user_victim
    from robustbench3d.victims.onnx.runtime import OnnxCascade

    OnnxCascade(args.directory)
    path = add_user_victim(args.name, args.directory, replace=args.replace)
    print(f"registered ONNX victim {args.name!r} -> {args.directory} (in {path})")
    return 0

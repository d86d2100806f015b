"""``robustbench3d victims remove NAME``: undo ``victims add-onnx``.

Deletes NAME from the user registry file (``<cache>/victims/onnx.json``); the ONNX directory itself
is left alone. In-tree, shipped and plugin victims are refused. Standard library only at module level.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", metavar="NAME", help="a victim registered with `victims add-onnx`")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.victims.onnx.registration import remove_user_victim

    path, directory = remove_user_victim(args.name)
    print(f"removed ONNX victim {args.name!r} (was {directory}) from {path}; the directory is left as it was")
    return 0

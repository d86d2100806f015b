"""``robustbench3d victims pack``: join the two trainers' outputs into one cascade weights file.

The file (``FPointNetCascade.save``) is what ships in ``robustbench3d/victims/weights/`` and what
``weights=`` of the F-PN victims loads; its sha256 is printed (and registered for shipped files).
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--yolo", required=True, metavar="FILE", help="model.pt of `robustbench3d train yolo`")
    parser.add_argument("--fpointnet", required=True, metavar="FILE",
                        help="model.pt of `robustbench3d train fpointnet`")
    parser.add_argument("--out", required=True, metavar="FILE", help="cascade weights file to write")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.fileio import sha256_file
    from robustbench3d.victims.cascade import FPointNetCascade

    FPointNetCascade.from_parts(args.yolo, args.fpointnet).save(args.out)
    print(f"{sha256_file(args.out)}  {args.out}")
    return 0

"""``robustbench3d attack apply``: an attacked copy of a dataset split in KITTI layout, for any detector
(the layout, resume and written-once rules: :mod:`robustbench3d.attacks.apply`).

``--seed`` is in [0, 2**32 - 1] and ``--max-frames`` in [1, 1000000], checked before any work.
Standard library only at module level.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("object", metavar="OBJECT", help="a registered attack name, or an object file NAME.ply")
    parser.add_argument("--data", metavar="DIR",
                        help="KITTI-layout dataset root (default: the embedded dataset, generated if missing)")
    parser.add_argument("--split", default="val", help="split name, ImageSets/<split>.txt (default: val)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory (resumes an interrupted run)")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help="run seed: the per-frame attack randomness, as in `run --seed`, in [0, 2**32 - 1] "
                             "(default 0)")
    parser.add_argument("--max-frames", type=int, metavar="N",
                        help="only the first N frames of the split (1 to 1000000)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.attacks.apply import apply_dataset

    out = Path(args.out)
    counts = apply_dataset(args.object, args.data, args.split, out, args.seed, args.max_frames,
                           progress=not args.no_progress)
    print(f"{out}: {counts['written']} frame(s) attacked ({counts['objects']} objects placed), "
          f"{counts['kept']} already complete")
    return 0

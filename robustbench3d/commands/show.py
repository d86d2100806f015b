"""``robustbench3d show``: a frame as a picture, for users and for checking generated data
(:func:`robustbench3d.draw.render`).

With ``--attack OBJECT`` (a registered attack or an object file) the frame is drawn clean (left) and
attacked (right), as ``attack apply`` attacks it (same seed and placement,
:func:`robustbench3d.attacks.apply.attacked_frame`): in the attacked bird's-eye view the object's LiDAR
returns are drawn in yellow (no class or height colour), enlarged to 3 x 3 px.

``--out`` is never replaced without ``--force``. ``--bev-range`` is in [:data:`~robustbench3d.draw.BEV_RANGE_M`]
m and ``--seed`` in [0, 2**32 - 1] (as ``run --seed``), both checked before the frame is read.
"""

from __future__ import annotations

import argparse

from robustbench3d.draw import BEV_RANGE_M


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("root", help="dataset root in KITTI layout (holds training/)")
    parser.add_argument("frame", help="frame id, e.g. 000001")
    parser.add_argument("--out", required=True, help="PNG file to write (an existing file only with --force)")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")
    parser.add_argument("--pred", help="optional result directory; its detections are drawn in red")
    parser.add_argument("--bev-range", type=float, default=70.0,
                        help=f"forward range of the BEV panel, m, in [{BEV_RANGE_M[0]:g}, {BEV_RANGE_M[1]:g}] "
                             "(default 70)")
    parser.add_argument("--attack", metavar="OBJECT",
                        help="also draw the frame attacked by OBJECT (registered attack or NAME.ply), side by side")
    parser.add_argument("--seed", type=int, default=0,
                        help="attack seed, as in `run`/`attack apply`, in [0, 2**32 - 1] (default 0)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from robustbench3d.attacks import resolve_attack
    from robustbench3d.attacks.spec import check_seed
    from robustbench3d.draw import bev_range_problem, render
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import check_output_file, replacing_note
    from robustbench3d.kitti import KittiDataset, read_labels
    from robustbench3d.kitti.image import write_image

    check_output_file(args.out, "--out", force=args.force)
    problem = bev_range_problem(args.bev_range)
    if problem is not None:
        raise RobustBenchError(f"--bev-range {args.bev_range}: {problem}")
    check_seed(args.seed)
    attack = resolve_attack(args.attack)[1] if args.attack else None
    ds = KittiDataset(args.root, split=None)
    frame = ds.frame(args.frame)
    dets = None
    if args.pred:
        from pathlib import Path

        path = Path(args.pred) / f"{args.frame}.txt"
        dets = read_labels(path, scored=True) if path.exists() else None
    picture = render(frame, dets, args.bev_range)
    if attack is not None:
        picture = np.concatenate([picture, _attacked_picture(ds, frame, attack, args.seed, dets,
                                                             args.bev_range)], axis=1)
    note = replacing_note(args.out)
    if note:
        print(note)
    write_image(args.out, picture)
    print(args.out)
    return 0


def _attacked_picture(ds, frame, reference, seed: int, dets, bev_range: float):
    from robustbench3d.attacks.apply import attacked_frame
    from robustbench3d.draw import render

    attacked, added = attacked_frame(ds, frame, reference, seed)
    return render(attacked, dets, bev_range, highlight=added)

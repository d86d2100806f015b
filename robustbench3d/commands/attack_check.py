"""``robustbench3d attack check``: an independent geometric check of an attacked dataset (``attack apply``);
what is checked and how: :mod:`robustbench3d.attacks.check`. ``--max-frames`` is an integer in [1, 1000000].

    robustbench3d attack check ATTACKED_DIR [--clean DIR] [--max-frames N]
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("attacked", metavar="ATTACKED_DIR", help="output directory of `attack apply`")
    parser.add_argument("--clean", metavar="DIR", help="the clean dataset (default: the manifest's dataset root)")
    parser.add_argument("--split", help="split to check (default: the manifest's)")
    parser.add_argument("--max-frames", type=int, metavar="N",
                        help="only the first N frames of the split (1 to 1000000)")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.attacks.check import check_attacked_dataset

    r = check_attacked_dataset(args.attacked, args.clean, args.split, args.max_frames)
    print(f"{r.frames} frames ({r.frames_with_objects} with objects): {r.added} points added "
          f"(max distance to the meshes {r.max_added_distance_m:.2e} m), {r.removed} removed, {r.kept} kept, "
          f"{r.changed_pixels} pixels changed; silhouette edge cases: {r.edge_removed} removed, {r.edge_kept} kept")
    for line in r.violations:
        print(f"FAIL {line}")
    print("PASS" if r.ok else f"FAIL: {len(r.violations)} violation(s)")
    return 0 if r.ok else 1

"""``robustbench3d victims parity VICTIM [--onnx DIR] [--data DIR] [--max-frames N]``: torch vs onnxruntime.

Without ``--onnx`` the victim is exported to a temporary directory first (``--exporter``). An F-PN cascade
is compared at three levels (:mod:`robustbench3d.victims.onnx.parity`; the ONNX victim runs with the torch
victim's seed and gather mode); ``pointpillars`` with its one-graph ONNX twin
(:func:`robustbench3d.victims.onnx.pointpillars_export.parity`: output maps, detections per frame, matched
detections' score / location / size / yaw, Car BEV AP R40 moderate; the twin decodes with the torch victim's
``score_threshold`` and ``max_detections``), judged by the cascade's tolerances (:data:`POINTPILLARS_CHECKS`).
Exit status 0 when every check passes, 1 otherwise; 2 on bad input. Checked before any work (no weights
loaded, no dataset generated): ``--onnx DIR`` (its manifest is of the victim's kind, every graph file has the
manifest's sha256), ``--json`` (a new file unless ``--force``), ``--max-frames`` (>= 1), ``--seed`` (in
:data:`~robustbench3d.victims.zoo.SEED_RANGE`), ``--proposals`` (``detector`` only for PointPillars) and the
``--victim-arg`` form. Standard library only at module level.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from robustbench3d.victims.onnx.torch_source import add_victim_arguments

#: The PointPillars parity checks: (label, field of the parity record, field of
#: :class:`~robustbench3d.victims.onnx.parity.Tolerances` bounding its |difference|). The output maps are
#: held to the cascade's stage-tensor tolerance, the matched detections to its box-level ones.
POINTPILLARS_CHECKS = (
    ("output maps max |Δ| (9 channels)", "max_output_diff", "tensor_atol"),
    ("heatmap logits max |Δ|", "max_heatmap_diff", "tensor_atol"),
    ("score max |Δ|", "max_score_diff", "score_atol"),
    ("location max |Δ| (m)", "max_location_diff", "geometry_atol"),
    ("dimensions max |Δ| (m)", "max_dimension_diff", "geometry_atol"),
    ("rotation_y max |Δ| (rad)", "max_rotation_diff", "geometry_atol"),
)

#: The fields of :class:`~robustbench3d.victims.onnx.parity.Tolerances` the PointPillars checks use.
PP_TOLERANCES = ("tensor_atol", "score_atol", "geometry_atol", "ap_atol")


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
    parser.add_argument("--proposals", metavar="SRC[,SRC]",
                        help="proposal sources compared at the box and AP levels (default: gt,detector; "
                             "pointpillars finds its own objects: detector only)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed= of the victim unless given by --victim-arg, 0 to 2**63-1 (default 0)")
    parser.add_argument("--json", metavar="PATH", help="also write the report as JSON (a new file unless --force)")
    parser.add_argument("--force", action="store_true", help="let --json replace an existing file")


def is_pointpillars(name: str) -> bool:
    """Whether the registered victim ``name`` is the PointPillars detector (compared with a one-graph twin);
    any other name, unknown ones included (refused when the victim is built), takes the cascade path."""
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims import VICTIMS, zoo

    try:
        return VICTIMS.get(name).factory is zoo.pointpillars
    except RobustBenchError:
        return False


def check_onnx_dir(directory: str, pointpillars: bool = False) -> None:
    """``--onnx DIR``, before any work: a directory holding a valid ``manifest.json`` of the victim's kind (F-PN
    cascade stages, or with ``pointpillars`` the PointPillars graph) whose graph files exist with the manifest's
    sha256 (:class:`~robustbench3d.errors.DataFormatError` naming the file)."""
    from robustbench3d.errors import DataFormatError
    from robustbench3d.victims.onnx import MANIFEST_FILE
    from robustbench3d.victims.onnx.manifest import POINTPILLARS_FORMAT, manifest_format, read_manifest, verify_files

    if pointpillars:
        check_pointpillars_dir(directory)
        return
    if Path(directory).is_dir() and manifest_format(directory) == POINTPILLARS_FORMAT:
        raise DataFormatError(Path(directory) / MANIFEST_FILE, "holds a PointPillars graph, not an F-PN cascade's "
                                                               "stages; compare it with victim pointpillars")
    verify_files(directory, read_manifest(directory))


def check_pointpillars_dir(directory: str) -> None:
    """A PointPillars ONNX twin directory (:mod:`robustbench3d.victims.onnx.pointpillars`): its manifest's format
    and graph entry, and the graph file's sha256 (the rest is checked when the twin loads)."""
    from robustbench3d.errors import DataFormatError
    from robustbench3d.fileio import read_user_text, sha256_file
    from robustbench3d.victims.onnx import MANIFEST_FILE
    from robustbench3d.victims.onnx.manifest import FORMAT, POINTPILLARS_FORMAT, manifest_format, stage_spec

    root = Path(directory)
    manifest = root / MANIFEST_FILE
    if not root.is_dir():
        raise DataFormatError(root, "ONNX victim directory not found")
    if not manifest.is_file():
        raise DataFormatError(manifest, "manifest not found; a PointPillars twin is written by "
                                        "`robustbench3d victims export-onnx pointpillars`")
    fmt = manifest_format(root)
    if fmt != POINTPILLARS_FORMAT:
        what = "an F-PN cascade's stages" if fmt == FORMAT else f"format {fmt!r}"
        raise DataFormatError(manifest, f"holds {what}, not a PointPillars graph ({POINTPILLARS_FORMAT!r}, "
                                        "written by `robustbench3d victims export-onnx pointpillars`)")
    spec = stage_spec(json.loads(read_user_text(manifest)).get("graph"), "graph", manifest)
    graph = root / spec.file
    if not graph.is_file():
        raise DataFormatError(graph, "graph file missing")
    if sha256_file(graph) != spec.sha256:
        raise DataFormatError(graph, f"sha256 does not match the manifest's {spec.sha256} (file changed or corrupt; "
                                     "re-export it)")


def _proposals(text: str | None, pointpillars: bool = False) -> list[str]:
    from robustbench3d.errors import RobustBenchError

    if pointpillars:
        if text is not None and [p.strip() for p in text.split(",") if p.strip()] != ["detector"]:
            raise RobustBenchError(f"--proposals: victim pointpillars finds its own objects; only detector is "
                                   f"compared (got {text!r})")
        return ["detector"]
    text = "gt,detector" if text is None else text
    proposals = [p.strip() for p in text.split(",") if p.strip()]
    if not proposals or any(p not in ("gt", "detector") for p in proposals):
        raise RobustBenchError(f"--proposals: choose from gt, detector (got {text!r})")
    return proposals


def _frames(args: argparse.Namespace) -> tuple[Any, Any, list[Any]]:
    """(the dataset split, its ground truth, its frames with labels), the first ``--max-frames``."""
    from robustbench3d.datasets import load_ground_truth, resolve_dataset
    from robustbench3d.kitti.dataset import Frame

    dataset = resolve_dataset(args.data, args.split)
    gt = load_ground_truth(dataset, args.max_frames)
    kitti = dataset.kitti()
    frames = [Frame(fid, kitti.image(fid), kitti.scan(fid), kitti.calib(fid), labels)
              for fid, labels in zip(gt.frame_ids, gt.labels, strict=True)]
    return dataset, gt, frames


def _write_json(args: argparse.Namespace, report: dict[str, Any]) -> None:
    from robustbench3d.fileio import atomic_write_text, replacing_note

    note = replacing_note(args.json)
    if note:
        print(note)
    atomic_write_text(args.json, json.dumps(report, indent=2, default=float) + "\n")


def run(args: argparse.Namespace) -> int:
    from robustbench3d.fileio import check_output_file
    from robustbench3d.registry import parse_kwargs
    from robustbench3d.victims.onnx import require
    from robustbench3d.victims.onnx.torch_source import check_int_option
    from robustbench3d.victims.zoo import SEED_RANGE

    if args.json:
        check_output_file(args.json, "--json", force=args.force)
    pointpillars = is_pointpillars(args.victim)
    if args.onnx:
        check_onnx_dir(args.onnx, pointpillars)
    check_int_option("--max-frames", args.max_frames, 1)
    check_int_option("--seed", args.seed, *SEED_RANGE)
    proposals = _proposals(args.proposals, pointpillars)
    kwargs = parse_kwargs(args.victim_arg, "--victim-arg")
    require("onnx")
    require("onnxruntime")
    if not args.onnx and args.exporter == "dynamo":
        require("onnxscript")
    kwargs.setdefault("seed", args.seed)
    if pointpillars:
        return _run_pointpillars(args, kwargs)
    return _run_cascade(args, kwargs, proposals)


def _run_cascade(args: argparse.Namespace, kwargs: dict[str, Any], proposals: list[str]) -> int:
    import tempfile

    from robustbench3d.victims.onnx.export import ExportOptions, describe_kwargs, export_cascade
    from robustbench3d.victims.onnx.parity import format_report, run_parity
    from robustbench3d.victims.onnx.runtime import OnnxCascade
    from robustbench3d.victims.onnx.torch_source import create_cascade

    victim = create_cascade(args.victim, kwargs)
    dataset, _, frames = _frames(args)
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
        _write_json(args, report.to_dict())
    return 0 if report.ok else 1


def _run_pointpillars(args: argparse.Namespace, kwargs: dict[str, Any]) -> int:
    """``pointpillars`` against its one-graph twin (module doc); the twin loads before the dataset is read."""
    import tempfile

    from robustbench3d.victims.onnx.export import ExportOptions, describe_kwargs
    from robustbench3d.victims.onnx.parity import Tolerances
    from robustbench3d.victims.onnx.pointpillars import PointPillarsOnnx
    from robustbench3d.victims.onnx.pointpillars_export import export_pointpillars, parity
    from robustbench3d.victims.onnx.torch_source import create_cascade

    victim = create_cascade(args.victim, kwargs, pointpillars=True)
    with tempfile.TemporaryDirectory(prefix="robustbench3d-onnx-") as tmp:
        directory = Path(args.onnx) if args.onnx else Path(tmp)
        if not args.onnx:
            export_pointpillars(victim, directory, ExportOptions(args.exporter),
                                source={"victim": args.victim, "kwargs": describe_kwargs(kwargs)},
                                reproduce_command="(temporary export by robustbench3d parity)")
        twin = PointPillarsOnnx(directory, score_threshold=victim.options.score_threshold,
                                max_detections=victim.options.max_detections)
        dataset, gt, frames = _frames(args)
        print(f"{args.victim} (torch) vs {directory if args.onnx else 'a temporary ' + args.exporter + ' export'} "
              f"(onnxruntime) on {len(frames)} frames of {dataset.root} split {args.split}")
        record = parity(victim, twin, frames, list(gt.labels))
    checks = pointpillars_checks(record, Tolerances())
    ok = all(c["ok"] for c in checks)
    print(format_pointpillars(record, checks, ok))
    if args.json:
        from dataclasses import asdict

        tol = Tolerances()
        _write_json(args, {"ok": ok, "victim": args.victim, "onnx": str(args.onnx) if args.onnx else None,
                           "tolerances": {k: getattr(tol, k) for k in PP_TOLERANCES},
                           "parity": _no_nan(asdict(record)), "checks": [_no_nan(c) for c in checks]})
    return 0 if ok else 1


def _no_nan(row: dict[str, Any]) -> dict[str, Any]:
    """``row`` with NaN values as None (JSON null: the file stays strict JSON)."""
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}


def pointpillars_checks(record: Any, tol: Any) -> list[dict[str, Any]]:
    """The PointPillars parity record (:class:`~robustbench3d.victims.onnx.pointpillars_export.PointPillarsParity`)
    judged by ``tol`` (:class:`~robustbench3d.victims.onnx.parity.Tolerances`): one row per check with ``value``,
    ``limit`` (text) and ``ok``. A NaN difference fails; the AP row passes when both APs are NaN (no Car labels:
    nothing to compare) or differ by at most ``ap_atol`` points."""
    rows = []
    for label, name, bound in POINTPILLARS_CHECKS:
        value, limit = float(getattr(record, name)), float(getattr(tol, bound))
        rows.append({"check": label, "value": value, "limit": f"<= {limit:g}", "ok": value <= limit})
    rows.insert(2, {"check": "detections per frame equal", "value": bool(record.same_counts),
                    "limit": f"all {record.frames} frames", "ok": bool(record.same_counts)})
    a, b = float(record.ap_torch), float(record.ap_onnx)
    both_nan = math.isnan(a) and math.isnan(b)
    rows.append({"check": "Car BEV AP R40 moderate |Δ| (points)", "value": abs(a - b),
                 "limit": "no Car labels" if both_nan else f"<= {tol.ap_atol:g}",
                 "ok": both_nan or abs(a - b) <= tol.ap_atol})
    return rows


def format_pointpillars(record: Any, checks: list[dict[str, Any]], ok: bool) -> str:
    """The checks as a plain-text table, both APs and the verdict line."""
    from robustbench3d.bench import dict_table

    return "\n".join(["== PointPillars torch vs ONNX twin: output maps, detections per frame, matched detections "
                      "(by rank), AP", dict_table(checks),
                      f"Car BEV AP R40 moderate: torch {record.ap_torch:.4f}, onnx {record.ap_onnx:.4f}",
                      f"parity: {'PASS' if ok else 'FAIL'}"])

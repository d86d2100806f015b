"""``robustbench3d victims pack``: join the two trainers' outputs into one cascade weights file.

The file (``FPointNetCascade.save``) is what ships in ``robustbench3d/victims/weights/`` and what
``weights=`` of the F-PN victims loads; its sha256 is printed. With ``--manifest`` and
``--victim`` the entry of that victim in the shipped-weights manifest
(:mod:`robustbench3d.victims.shipped`) is written too: file, sha256, size, each network's
configuration and parameter count, each training run's configuration and last validation record
(read from the trainers' output directories; a fine-tuning run also records the run it started
from), the reproduction script, the environment, and —
with ``--summary`` — the accuracy measured by a ``robustbench3d run`` that used this very file
(checked through the run's recorded weight hashes).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--yolo", required=True, metavar="FILE", help="model.pt of `robustbench3d train yolo`")
    parser.add_argument("--fpointnet", required=True, metavar="FILE",
                        help="model.pt of `robustbench3d train fpointnet`")
    parser.add_argument("--out", required=True, metavar="FILE", help="cascade weights file to write")
    parser.add_argument("--manifest", metavar="FILE", type=Path,
                        help="shipped-weights manifest to update (victims/weights/manifest.json)")
    parser.add_argument("--victim", help="victim name of the manifest entry (with --manifest)")
    parser.add_argument("--summary", metavar="FILE", type=Path,
                        help="summary.json of a `run` that used --out as weights: its clean cells become the "
                             "entry's measured accuracy")
    parser.add_argument("--reproduce", metavar="FILE", type=Path,
                        help="the script that reproduces the weights (recorded with its commands)")


def _training_record(model_file: Path, network: str, earlier: list[dict[str, Any]], depth: int = 0) -> dict[str, Any]:
    """Run configuration and validation history of a trainer's output directory. A fine-tuning run
    (``init``) also records the run it started from, as ``"init"``: read from that file's
    directory if it is still there, else from an ``earlier`` manifest entry with its sha256."""
    import json

    import torch

    from robustbench3d.victims.training import CHECKPOINT, LOG

    run_dir = model_file.parent
    record: dict[str, Any] = {"model_file": model_file.name}
    ckpt = run_dir / CHECKPOINT
    if ckpt.is_file():
        data = torch.load(ckpt, map_location="cpu", weights_only=False)
        record["run_config"] = data["run_config"]
        record["steps"] = data["state"]["step"]
    log = run_dir / LOG
    if log.is_file():
        history = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines() if line.strip()]
        record["epochs"] = len(history)
        record["last_validation"] = {k: v for k, v in history[-1].items() if k.startswith("val_")} if history else {}
    task = record.get("run_config", {}).get("task", {})
    init, init_sha = task.get("init"), task.get("init_sha256")
    if init and depth < 8:
        source = next((e for e in earlier if e.get("sha256") == init_sha), None)
        if Path(init).is_file() and (Path(init).parent / CHECKPOINT).is_file():  # a trainer's output
            record["init"] = {"file": init, "sha256": init_sha,
                              **_training_record(Path(init), network, earlier, depth + 1)}
        elif source is not None:
            record["init"] = {"file": source["file"], "sha256": init_sha, "victim": source["victim"],
                              **source.get("training", {}).get(network, {})}
        else:
            record["init"] = {"file": init, "sha256": init_sha, "note": "its training record was not found"}
    return record


def _accuracy(summary_file: Path, victim_name: str, weights_sha: str) -> dict[str, Any]:
    """AP of the victim's clean cells in the run summary, refusing a run that did not use the
    packed file."""
    import json

    from robustbench3d.errors import RobustBenchError

    cells = json.loads(summary_file.read_text(encoding="utf-8"))
    out: dict[str, Any] = {"summary": str(summary_file), "cells": {}}
    for cell in cells:
        if cell["victim"] != victim_name or cell["attack"] != "none" or cell["status"] != "ok":
            continue
        victim = cell["provenance"]["config"]["victim"]
        hashes = set(victim.get("weight_files", {}).values()) | {victim.get("weights_sha256")}
        if weights_sha not in hashes:
            raise RobustBenchError(f"{summary_file}: cell {cell['victim']}+{cell['proposals']} did not run with "
                                   f"the packed weights (sha256 {weights_sha})")
        car = cell["metrics"]["Car"]
        out["cells"][cell["proposals"]] = {m: car[m] for m in ("2d", "bev", "3d") if m in car}
        out["dataset"] = cell["dataset"]
    return out


def run(args: argparse.Namespace) -> int:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import sha256_file
    from robustbench3d.victims.cascade import FPointNetCascade

    if args.manifest is not None and not args.victim:
        raise RobustBenchError("--manifest needs --victim NAME")
    cascade = FPointNetCascade.from_parts(args.yolo, args.fpointnet)
    cascade.save(args.out)
    sha = sha256_file(args.out)
    print(f"{sha}  {args.out}")
    if args.manifest is None:
        return 0

    from robustbench3d.provenance import host_provenance
    from robustbench3d.victims.fpointnet.model import count_parameters
    from robustbench3d.victims.shipped import read_manifest, upsert_entry

    out = Path(args.out)
    earlier = read_manifest(args.manifest)["weights"]
    entry: dict[str, Any] = {
        "victim": args.victim, "file": out.name, "sha256": sha, "size_bytes": out.stat().st_size,
        "networks": {
            "yolo": {"config": cascade.yolo.cfg.to_dict(), "parameters": count_parameters(cascade.yolo.net)},
            "fpointnet": {"config": cascade.fpn.cfg.to_dict(), "parameters": count_parameters(cascade.fpn)},
        },
        "training": {name: _training_record(Path(path), name, earlier)
                     for name, path in (("yolo", args.yolo), ("fpointnet", args.fpointnet))},
        "environment": host_provenance(),
    }
    if args.reproduce is not None:
        lines = args.reproduce.read_text(encoding="utf-8").splitlines()
        entry["reproduce"] = {"script": args.reproduce.name,
                              "commands": [ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]}
    if args.summary is not None:
        entry["accuracy"] = _accuracy(args.summary, args.victim, sha)
        if not entry["accuracy"]["cells"]:
            raise RobustBenchError(f"{args.summary}: no finished clean cell of victim {args.victim!r}")
    upsert_entry(args.manifest, entry)
    print(f"manifest entry {args.victim!r} written to {args.manifest}")
    return 0

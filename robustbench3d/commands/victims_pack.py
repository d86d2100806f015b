"""``robustbench3d victims pack``: join the two trainers' outputs into one cascade weights file.

The file (``FPointNetCascade.save``) is what ships in ``robustbench3d/victims/weights/`` and what
``weights=`` of the F-PN victims loads; its sha256 is printed. With ``--manifest`` and
``--victim`` the entry of that victim in the shipped-weights manifest
(:mod:`robustbench3d.victims.shipped`) is written too: file, sha256, size, each network's
configuration and parameter count, each training run's configuration and last validation record
(read from the trainers' output directories; a fine-tuning run also records the run it started
from), the reproduction script, the environment, and —
with ``--summary`` — the accuracy measured by a ``robustbench3d run`` that used this very file
(checked through the run's recorded weight hashes). Every torch file (weights, ``last.pt``, the
files ``init`` names) is read as data only (:mod:`robustbench3d.victims.torchfile`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--yolo", required=True, metavar="FILE",
                        help="model.pt of `robustbench3d victims train-yolo` (or a cascade weights file: its YOLO)")
    parser.add_argument("--fpointnet", required=True, metavar="FILE",
                        help="model.pt of `robustbench3d victims train-fpointnet` (or a cascade weights file: its "
                             "F-PN)")
    parser.add_argument("--out", required=True, metavar="FILE", help="cascade weights file to write")
    parser.add_argument("--yolo-shared", action="store_true",
                        help="refer to the --yolo file (in --out's directory) for the 2D-stage weights instead of "
                             "copying them, as fpointnet-v1.pt does with fpointnet-v1-lite.pt")
    parser.add_argument("--manifest", metavar="FILE", type=Path,
                        help="shipped-weights manifest to update (victims/weights/manifest.json)")
    parser.add_argument("--victim", help="victim name of the manifest entry (with --manifest)")
    parser.add_argument("--summary", metavar="FILE", type=Path,
                        help="summary.json of a `run` that used --out as weights: its clean cells become the "
                             "entry's measured accuracy")
    parser.add_argument("--yolo-option", action="append", default=[], metavar="KEY=VALUE",
                        help="set an inference field of the YOLO config (conf_threshold, nms_threshold, nms_merge, "
                             "flip_tta, max_detections; VALUE is JSON); repeatable")
    parser.add_argument("--reproduce", metavar="FILE", type=Path,
                        help="the script that reproduces the weights (recorded with its commands)")


def yolo_options(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` inference options of the YOLO config, values parsed as JSON."""
    import json

    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims.yolo.config import INFERENCE_FIELDS, YoloConfig

    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in INFERENCE_FIELDS:
            raise RobustBenchError(f"--yolo-option {item!r}: expected KEY=VALUE with KEY one of "
                                   f"{', '.join(INFERENCE_FIELDS)}")
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError as exc:
            raise RobustBenchError(f"--yolo-option {item!r}: VALUE is not JSON ({exc.msg})") from None
        kind = type(getattr(YoloConfig(), key))
        allowed = (int, float) if kind is float else kind
        if isinstance(parsed, bool) != (kind is bool) or not isinstance(parsed, allowed):
            raise RobustBenchError(f"--yolo-option {item!r}: {key} takes a {kind.__name__}")
        out[key] = parsed
    return out


def _known_record(earlier: list[dict[str, Any]], network: str, *, state_sha: str | None = None,
                  file_sha: str | None = None, victim: str | None = None) -> dict[str, Any] | None:
    """The training record of ``network`` in the earlier manifest entry holding these weights
    (by network hash, or — for entries written before network hashes — by file hash), with the
    entry it came from as ``recorded_in`` unless that is ``victim``'s own (earlier) entry."""
    for e in earlier:
        net = e.get("networks", {}).get(network, {})
        same_file = bool(file_sha) and e.get("sha256") == file_sha
        if (state_sha and net.get("state_sha256") == state_sha) or same_file:
            record = dict(e.get("training", {}).get(network, {}))
            if e.get("victim") != victim and "recorded_in" not in record:
                record["recorded_in"] = {"victim": e["victim"], "file": e["file"], "sha256": e["sha256"]}
            return record
    return None


def _training_record(model_file: Path, network: str, state_sha: str, earlier: list[dict[str, Any]],
                     victim: str | None = None, depth: int = 0) -> dict[str, Any]:
    """How ``network`` (weights hash ``state_sha``, from ``model_file``) was trained: the record of
    an earlier manifest entry with the same weights, else the run configuration and last
    validation of the trainer directory holding ``model_file``. A fine-tuning run (``init``) also
    records the run it started from, as ``"init"`` (looked up the same way)."""
    import json

    from robustbench3d.fileio import sha256_file
    from robustbench3d.victims.torchfile import load_network_part, network_sha256
    from robustbench3d.victims.training import CHECKPOINT, LOG, read_checkpoint

    known = _known_record(earlier, network, state_sha=state_sha, file_sha=sha256_file(model_file), victim=victim)
    if known is not None:
        return known
    run_dir = model_file.parent
    record: dict[str, Any] = {"model_file": model_file.name}
    ckpt = run_dir / CHECKPOINT
    if ckpt.is_file():
        data = read_checkpoint(ckpt)
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
        source = _known_record(earlier, network, file_sha=init_sha)
        if source is None and Path(init).is_file() and sha256_file(Path(init)) == init_sha:
            part = load_network_part(Path(init), network)
            source = _training_record(Path(init), network, network_sha256(part["state_dict"]), earlier,
                                      depth=depth + 1)
        record["init"] = {"file": init, "sha256": init_sha,
                          **(source if source is not None else {"note": "its training record was not found"})}
    return record


def _accuracy(summary_file: Path, victim_name: str, weights_sha: str) -> dict[str, Any]:
    """AP of the victim's clean cells in the run summary, refusing a run that did not use the
    packed file."""
    import json

    from robustbench3d.errors import RobustBenchError
    from robustbench3d.eval.rules import TARGET_CLASS
    from robustbench3d.results import CellResult

    out: dict[str, Any] = {"summary": str(summary_file), "cells": {}}
    for cell in map(CellResult, json.loads(summary_file.read_text(encoding="utf-8"))):
        if cell.victim != victim_name or cell.attack != "none" or not cell.ok:
            continue
        victim = cell.config["victim"]
        hashes = set(victim.get("weight_files", {}).values()) | {victim.get("weights_sha256")}
        if weights_sha not in hashes:
            raise RobustBenchError(f"{summary_file}: cell {cell.victim}+{cell.proposals} did not run with "
                                   f"the packed weights (sha256 {weights_sha})")
        result = cell.result
        assert result is not None  # an ok cell has metrics
        out["cells"][cell.proposals] = {m: result.data[TARGET_CLASS][m] for m in ("2d", "bev", "3d")
                                        if m in result.metrics(TARGET_CLASS)}
        out["dataset"] = dict(cell.dataset)
    return out


def run(args: argparse.Namespace) -> int:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.fileio import check_output_file, sha256_file
    from robustbench3d.victims.cascade import FPointNetCascade
    from robustbench3d.victims.torchfile import load_network_part, network_sha256

    if args.manifest is not None and not args.victim:
        raise RobustBenchError("--manifest needs --victim NAME")
    check_output_file(args.out, "--out")
    if args.manifest is not None:
        check_output_file(args.manifest, "--manifest")
    from robustbench3d.victims.fpointnet.model import count_parameters
    from robustbench3d.victims.shipped import read_manifest, upsert_entry

    sources = {"yolo": Path(args.yolo), "fpointnet": Path(args.fpointnet)}
    parts = {name: load_network_part(path, name) for name, path in sources.items()}
    parts["yolo"] = {**parts["yolo"], "config": {**parts["yolo"]["config"], **yolo_options(args.yolo_option)}}
    cascade = FPointNetCascade.from_parts(parts["yolo"], parts["fpointnet"], origins=(sources["yolo"],
                                                                                      sources["fpointnet"]))
    networks = {name: {"config": part["config"], "state_sha256": network_sha256(part["state_dict"])}
                for name, part in parts.items()}
    training: dict[str, Any] = {}
    if args.manifest is not None:  # read before --out is written: it may replace one of the sources
        earlier = read_manifest(args.manifest)["weights"]
        training = {name: _training_record(path, name, networks[name]["state_sha256"], earlier, args.victim)
                    for name, path in sources.items()}
    cascade.save(args.out, share_yolo=sources["yolo"] if args.yolo_shared else None)
    sha = sha256_file(args.out)
    print(f"{sha}  {args.out}")
    if args.manifest is None:
        return 0

    from robustbench3d.provenance import host_provenance

    out = Path(args.out)
    networks["yolo"]["parameters"] = count_parameters(cascade.yolo.net)
    networks["fpointnet"]["parameters"] = count_parameters(cascade.fpn)
    entry: dict[str, Any] = {
        "victim": args.victim, "file": out.name, "sha256": sha, "size_bytes": out.stat().st_size,
        "networks": networks, "training": training, "environment": host_provenance(),
    }
    if args.yolo_shared:
        entry["shared"] = {"yolo": {"file": sources["yolo"].name, "sha256": sha256_file(sources["yolo"])}}
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

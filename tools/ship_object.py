"""Ship a trained universal object: copy it into the package and (re)write its manifest entry.

    python tools/ship_object.py NAME OBJ.ply [--eval SUMMARY.json] [--command "robustbench3d attack train ..."]
        [--objects-dir DIR]

``OBJ.ply`` and its sidecar ``OBJ.json`` (as ``robustbench3d attack train`` wrote them) are checked
(:func:`robustbench3d.attacks.objectfile.read_object_file`), copied byte for byte to ``DIR/NAME.ply`` and
``DIR/NAME.json`` (default DIR: the package's ``attacks/objects``), and the entry ``NAME`` of
``DIR/manifest.json`` is replaced: hashes and sizes, a summary line, the training record (the sidecar's
``made_by`` plus the ``attack train`` command, rebuilt from the recorded config unless ``--command`` is
given) and, with ``--eval``, the evaluation: the cells of a ``robustbench3d run`` summary.json that ran
this very object (matched by its PLY sha256), or any other JSON object, kept as it is; without ``--eval``
the evaluation already recorded for the same bytes is kept. Every file is written atomically, the manifest
last.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
import sys
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

from robustbench3d.attacks.objectfile import read_object_file, sidecar_path
from robustbench3d.attacks.shipped import (
    MANIFEST_NAME,
    empty_manifest,
    objects_dir,
    read_manifest,
    upsert_entry,
    validate_manifest,
)
from robustbench3d.errors import RobustBenchError
from robustbench3d.fileio import atomic_write_bytes

TRAIN_TOOL = "robustbench3d attack train"
#: Config fields and the ``attack train`` option that sets them (value options; booleans below).
_OPTIONS = {"steps": "--steps", "seed": "--seed", "batch_cars": "--batch-cars", "lr_shape": "--lr-shape",
            "lr_color": "--lr-color", "lambda_lap": "--lambda-lap", "lambda_img": "--lambda-img",
            "eot": "--eot", "occlusion": "--occlusion", "lidar_boxes": "--lidar-boxes",
            "lidar_loss": "--lidar-loss", "lambda_box": "--lambda-box", "image_loss": "--image-loss",
            "eval_every": "--eval-every", "eval_frames": "--eval-frames", "plateau_window": "--plateau-window",
            "plateau_tol": "--plateau-tol"}
#: Config fields that do not change the object (left out of the command).
_IRRELEVANT = ("mode", "checkpoint_every")
#: Always written, even at their default value.
_ALWAYS = ("steps", "seed")


def training_command(name: str, made_by: dict[str, Any]) -> str:
    """The ``robustbench3d attack train`` command that reproduces the object described by ``made_by`` (a
    sidecar's): ``--steps`` and ``--seed`` always, every other option only where the config differs from
    the default; the embedded dataset is ``--data "$DATA"``, the output ``--out "$OUT/NAME.ply"`` (the
    variables of ``attacks/objects/reproduce.sh``). Raises :class:`RobustBenchError` for a config an
    option cannot express (give ``--command``)."""
    from robustbench3d.attacks.train_config import RECORD_DEFAULTS, TrainConfig

    config = {**RECORD_DEFAULTS, **made_by["config"]}  # fields the record predates: the values it implies
    defaults = asdict(TrainConfig(mode=config["mode"]))
    defaults["eot"] = list(defaults["eot"])
    unknown = sorted(set(config) - {f.name for f in fields(TrainConfig)})
    if unknown:
        raise RobustBenchError(f"config fields {', '.join(unknown)} are not TrainConfig's; give --command")
    parts = [*TRAIN_TOOL.split(), config["mode"], "--victim", made_by["victim"]["name"]]
    for key, value in sorted((made_by["victim"].get("kwargs") or {}).items()):
        parts += ["--victim-arg", f"{key}={value}"]
    data = made_by.get("training_data") or {}
    parts += ["--data", "$DATA"] if data.get("embedded") else ["--data", str(data["root"])]
    if data.get("split", "train") != "train":
        parts += ["--split", data["split"]]
    if data.get("frames") is not None and data.get("frames") != data.get("split_frames"):
        parts += ["--max-frames", str(data["frames"])]
    parts += ["--out", f"$OUT/{name}.ply"]
    for key in sorted(config, key=lambda k: (_ALWAYS.index(k) if k in _ALWAYS else len(_ALWAYS), k)):
        value = config[key]
        if key in _IRRELEVANT or (value == defaults[key] and key not in _ALWAYS):
            continue
        if key == "use_class":
            parts.append("--no-class-prob")
        elif key == "eot":
            parts += ["--eot", ",".join(value)]
        elif key in _OPTIONS:
            parts += [_OPTIONS[key], str(value)]
        else:
            raise RobustBenchError(f"config field {key!r} = {value!r} differs from the default {defaults[key]!r} "
                                   "and no attack train option sets it; give --command")
    parts.append("--no-progress")
    return " ".join(f'"{p}"' if p.startswith("$") else shlex.quote(p) for p in parts)


def evaluation_record(path: Path, sha256: str) -> dict[str, Any]:
    """The evaluation of the object with PLY hash ``sha256`` from ``path``: of a run summary (a list of
    cells) the finished cells whose attack object is this file (Car metrics and attack effect per cell, and
    the dataset); any other JSON object as it is. Raises :class:`RobustBenchError` when a summary has no
    such cell."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RobustBenchError(f"{path}: cannot read the evaluation ({exc})") from None
    if isinstance(data, dict):
        return {"source": path.name, **data}
    if not isinstance(data, list):
        raise RobustBenchError(f"{path}: expected a run summary (a list of cells) or a JSON object")
    out: dict[str, Any] = {"summary": path.name, "cells": {}}
    for cell in data:
        attack = cell["provenance"]["config"]["attack"]
        described = attack.get("object") or {}  # the attack's describe(): its "object" names the PLY
        if cell["status"] != "ok" or (described.get("object") or {}).get("ply_sha256") != sha256:
            continue
        key = f"{cell['victim']}+{cell['attack']}+{cell['proposals']}"
        car = cell["metrics"]["Car"]
        out["cells"][key] = {"victim": cell["victim"], "attack": cell["attack"], "proposals": cell["proposals"],
                             "params": attack.get("params", {}),
                             "metrics": {m: car[m] for m in ("2d", "bev", "3d") if m in car},
                             "attack_effect": cell.get("attack_effect")}
        out["dataset"] = cell["dataset"]
    if not out["cells"]:
        raise RobustBenchError(f"{path}: no finished cell ran the object with sha256 {sha256}")
    return out


def summary_line(name: str, made_by: dict[str, Any]) -> str:
    """One line for attack listings."""
    victim = made_by["victim"]["name"]
    return (f"universal {made_by['attack']} object trained against {victim} ({made_by['steps']} steps, "
            f"seed {made_by['seed']}; shipped {name}.ply)")


def ship(name: str, ply: Path, directory: Path, evaluation: Path | None = None,
         command: str | None = None) -> dict[str, Any]:
    """Copy ``ply`` and its sidecar to ``directory`` as ``name`` and write the manifest entry (returned)."""
    loaded = read_object_file(ply)
    made_by = loaded.made_by
    side = sidecar_path(ply)
    if made_by.get("tool") != TRAIN_TOOL:
        raise RobustBenchError(f"{side}: made_by.tool is {made_by.get('tool')!r}; only objects written by "
                               f"{TRAIN_TOOL!r} ship (their sidecar records the training)")
    record: dict[str, Any] = {
        "name": name, "file": f"{name}.ply", "sha256": loaded.sha256, "size_bytes": None,
        "sidecar": {"file": f"{name}.json", "sha256": None, "size_bytes": None},
        "summary": summary_line(name, made_by),
        "training": {"command": command or training_command(name, made_by), **made_by},
        "reproduce": {"script": "reproduce.sh"},
    }
    manifest = directory / MANIFEST_NAME
    if evaluation is not None:
        record["evaluation"] = evaluation_record(evaluation, loaded.sha256)
    else:  # reshipping the same bytes keeps the evaluation recorded for them
        earlier = next((e for e in read_manifest(manifest)["objects"] if e["name"] == name), None)
        if earlier is not None and earlier["sha256"] == loaded.sha256 and "evaluation" in earlier:
            record["evaluation"] = earlier["evaluation"]
    raw_ply, raw_side = ply.read_bytes(), side.read_bytes()
    if hashlib.sha256(raw_ply).hexdigest() != loaded.sha256:
        raise RobustBenchError(f"{ply}: changed while shipping it")
    record["size_bytes"] = len(raw_ply)
    record["sidecar"].update(sha256=hashlib.sha256(raw_side).hexdigest(), size_bytes=len(raw_side))
    validate_manifest({**empty_manifest(), "objects": [record]}, manifest)  # refuse before writing anything
    atomic_write_bytes(directory / record["file"], raw_ply)
    atomic_write_bytes(directory / record["sidecar"]["file"], raw_side)
    upsert_entry(manifest, record)
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("name", metavar="NAME", help="attack name it ships as (adv-shape, adv-texture, adv-object)")
    parser.add_argument("ply", metavar="OBJ.ply", type=Path, help="object file written by attack train")
    parser.add_argument("--eval", type=Path, metavar="SUMMARY.json",
                        help="run summary.json with cells of this object, or a JSON object of its evaluation")
    parser.add_argument("--command", help="the attack train command (default: rebuilt from the sidecar's config)")
    parser.add_argument("--objects-dir", type=Path, default=objects_dir(), metavar="DIR",
                        help="where the shipped objects and manifest.json live (default: the package's)")
    args = parser.parse_args(argv)
    try:
        record = ship(args.name, args.ply, args.objects_dir, args.eval, args.command)
    except RobustBenchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"{record['sha256']}  {args.objects_dir / record['file']}")
    print(f"manifest entry {args.name!r} written to {args.objects_dir / MANIFEST_NAME}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

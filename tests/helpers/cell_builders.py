"""Hand-made summary cells for the runner's, the gate's and the tables' tests (schema-valid, every field spelled
out), and run directories holding them."""

from __future__ import annotations

import json
from pathlib import Path

from robustbench3d.results import validate_summary


def hand_provenance(victim: str, attack: str, proposals: str, fingerprint: str, *,
                    weights_sha256: str | None = None, evaluation: dict | None = None) -> dict:
    """Minimal schema-valid provenance of a hand-made cell: the configuration of ``victim`` (no arguments, weights
    ``weights_sha256``), ``attack`` (no parameters or requirements) and ``proposals``, a one-cell run and fixed
    package, versions, platform and times; ``evaluation``: the configuration's evaluation entry (default empty)."""
    return {
        "fingerprint": fingerprint,
        "config": {"victim": {"name": victim, "origin": "x", "kwargs": {}, "capabilities": None,
                              "weights_sha256": weights_sha256, "weight_files": {}},
                   "attack": {"name": attack, "origin": "x", "params": {}, "object": {},
                              "requirements": {"needs_gradients": False, "needs_camera": False, "needs_lidar": False}},
                   "proposals": proposals, "dataset": {}, "seed": 0, "batch_size": 1,
                   "evaluation": dict(evaluation or {})},
        "run": {"victims": [victim], "attacks": [attack], "proposals": [proposals]},
        "package": {"name": "robustbench3d", "version": "0"}, "git": {"commit": None, "dirty": None},
        "versions": {"python": "3", "numpy": "2", "torch": None, "onnxruntime": None},
        "platform": {"system": "Linux", "machine": "x", "cpu": None, "cpu_count": 2}, "seed": 0,
        "determinism": {}, "started": "2026-01-01T00:00:00Z", "finished": "2026-01-01T00:00:01Z", "seconds": 1.0}


def hand_cell(attack: str, metrics: dict, fingerprint: str, sha256: str) -> dict:
    """An ``ok`` cell of victim ``v`` with the detector's proposals, ``metrics`` (the evaluator's JSON, whose
    ``meta.frames`` sets the dataset's frames), a dataset with labels ``sha256`` and minimal provenance."""
    frames = metrics["meta"]["frames"]
    return {
        "schema_version": 1, "victim": "v", "attack": attack, "proposals": "detector", "status": "ok", "reason": None,
        "dataset": {"root": "/d", "split": "val", "frames": frames, "split_frames": frames, "sha256": sha256,
                    "embedded": None, "manifest": None},
        "metrics": metrics,
        "provenance": hand_provenance("v", attack, "detector", fingerprint),
    }


def write_run(root: Path, cells: list[dict], indent: int | None = None) -> Path:
    """``root`` made a run directory holding ``cells`` (schema-checked first) as its ``summary.json``
    (``json.dumps`` with ``indent``); returns ``root``."""
    validate_summary(cells)
    root.mkdir(parents=True, exist_ok=True)
    (root / "summary.json").write_text(json.dumps(cells, indent=indent), encoding="utf-8")
    return root

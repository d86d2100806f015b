"""Hand-made summary cells for the runner's tests (schema-valid, every field spelled out)."""

from __future__ import annotations


def hand_cell(attack: str, metrics: dict, fingerprint: str, sha256: str) -> dict:
    """An ``ok`` cell of victim ``v`` with the detector's proposals, ``metrics`` (the evaluator's JSON, whose
    ``meta.frames`` sets the dataset's frames), a dataset with labels ``sha256`` and minimal provenance."""
    frames = metrics["meta"]["frames"]
    return {
        "schema_version": 1, "victim": "v", "attack": attack, "proposals": "detector", "status": "ok", "reason": None,
        "dataset": {"root": "/d", "split": "val", "frames": frames, "split_frames": frames, "sha256": sha256,
                    "embedded": None, "manifest": None},
        "metrics": metrics,
        "provenance": {
            "fingerprint": fingerprint, "config": {"victim": {"name": "v", "origin": "x", "kwargs": {},
                                                              "capabilities": None, "weights_sha256": None,
                                                              "weight_files": {}},
                                                   "attack": {"name": attack, "origin": "x", "params": {}, "object": {},
                                                              "requirements": {"needs_gradients": False,
                                                                               "needs_camera": False,
                                                                               "needs_lidar": False}},
                                                   "proposals": "detector", "dataset": {}, "seed": 0, "batch_size": 1,
                                                   "evaluation": {}},
            "run": {"victims": ["v"], "attacks": [attack], "proposals": ["detector"]},
            "package": {"name": "robustbench3d", "version": "0"}, "git": {"commit": None, "dirty": None},
            "versions": {"python": "3", "numpy": "2", "torch": None, "onnxruntime": None},
            "platform": {"system": "Linux", "machine": "x", "cpu": None, "cpu_count": 2}, "seed": 0,
            "determinism": {}, "started": "2026-01-01T00:00:00Z", "finished": "2026-01-01T00:00:01Z", "seconds": 1.0},
    }

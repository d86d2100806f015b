"""Hand-made summary cells of Car BEV AP (percent) for the seed table's tests
(``tests/report/test_seed_table.py``, and the LiDAR-only rows of ``tests/attacks/test_frustum_protocols.py``)."""

from __future__ import annotations

from cell_builders import hand_provenance

SHA = "ab" * 32
DIFFS = ("easy", "moderate", "hard")


def by_diff(values: tuple[float, ...]) -> dict[str, float]:
    return dict(zip(DIFFS, values, strict=True))


def cell(victim: str, attack: str, proposals: str, r40: tuple[float, ...] | None = None,
         r11: tuple[float, ...] | None = None, frames: int = 12, status: str = "ok") -> dict:
    """A schema-valid summary cell with Car BEV AP (percent); ``status`` other than ok has no metrics."""
    metrics = None
    if status == "ok":
        metrics = {"Car": {"bev": {"R40": by_diff(r40), "R11": by_diff(r11)}},
                   "meta": {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent", "frames": frames,
                            "classes": ["Car"], "metrics": ["bev"], "min_overlap": {"Car": {"bev": 0.7}}}}
    return {
        "schema_version": 1, "victim": victim, "attack": attack, "proposals": proposals, "status": status,
        "reason": None if status == "ok" else "victim supports proposals detector only",
        "dataset": {"root": "/d", "split": "val", "frames": frames, "split_frames": frames, "sha256": SHA,
                    "embedded": None, "manifest": None},
        "metrics": metrics,
        "provenance": hand_provenance(victim, attack, proposals, SHA),
    }


def attacked(victim: str, attack: str, proposals: str, r40: tuple, r11: tuple, clean40: tuple, clean11: tuple,
             drop40: tuple, drop11: tuple, rel40: tuple, rel11: tuple, matched: int, missed: int) -> dict:
    """An attacked cell with its ``attack_effect`` written out by hand (clean AP, drop, relative drop, ASR)."""
    c = cell(victim, attack, proposals, r40, r11)

    def table(r40v: tuple, r11v: tuple) -> dict:
        return {"Car": {"bev": {"R40": by_diff(r40v), "R11": by_diff(r11v)}}}

    c["attack_effect"] = {
        "clean_cell": f"{victim}+none+{proposals}", "clean_fingerprint": SHA,
        "clean": table(clean40, clean11), "drop": table(drop40, drop11), "relative_drop": table(rel40, rel11),
        "success": {"class": "Car", "metric": "bev", "iou": 0.7, "difficulty": "moderate", "score_threshold": 0.5,
                    "clean_matched": matched, "attacked_missed": missed,
                    "rate": missed / matched if matched else None},
    }
    return c

"""``robustbench3d report --sweep DIR``: the sweep's section (figure, table, sentences, provenance) in the
markdown and in the page, which opens in headless Chromium with the figure shown; a bad sweep file is refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from browser import chromium_page

from robustbench3d.cli import main

ARTIFACTS = Path(__file__).resolve().parents[2] / ".pytest-artifacts"


def _score(name, kind, level, radius, proposals, rel, asr):
    return {"victim": "fpointnet-v1-lite", "proposals": proposals, "attack": name, "kind": kind, "name": name,
            "level": level, "radius": radius, "vertex_colours": None if level is None else 10 * 4 ** level + 2,
            "seed_point": name == "adv-texture-l2-r0.40", "status": "ok", "reason": None, "clean_ap": 90.0,
            "attacked_ap": 90.0 * (1 - rel), "drop": 90.0 * rel, "drop_ci": [80 * rel, 100 * rel],
            "relative_drop": rel, "relative_drop_ci": [0.8 * rel, 1.2 * rel], "asr": asr,
            "asr_ci": [0.5 * asr, 1.5 * asr], "seconds": 3.0, "cpu_seconds": 2.5}


def _sweep_doc() -> dict:
    scores, points = [], []
    for proposals in ("detector", "gt"):
        for level in (2, 4):
            for radius in (0.2, 0.4, 0.6):
                rel = 0.1 * level * radius * (1 if proposals == "detector" else 0.2)
                scores.append(_score(f"adv-texture-l{level}-r{radius:.2f}", "object", level, radius, proposals,
                                     rel, rel / 2))
        for radius in (0.2, 0.4, 0.6):
            name = "benign-sphere" if radius == 0.4 else f"benign-sphere-r{radius:.2f}"
            scores.append(_score(name, "benign", None, radius, proposals, 0.01 * radius, 0.02))
    for level in (2, 4):
        for radius in (0.2, 0.4, 0.6):
            points.append({"name": f"adv-texture-l{level}-r{radius:.2f}", "level": level, "radius": radius,
                           "vertex_colours": 10 * 4 ** level + 2, "seed_point": (level, radius) == (2, 0.4),
                           "training": {"steps": 150, "object_step": 100, "stopped": "plateau"},
                           "cost": {"train_wall_s": 600.0, "train_cpu_s": 590.0, "score_wall_s": 30.0}})
    return {"format": "robustbench3d.sweep/1",
            "config": {"victim": "fpointnet-v1-lite", "mode": "adv-texture", "seed": 0, "train_split": "train"},
            "dataset": {"frames": 25, "split": "val", "sha256": "ab" * 32}, "training_data": {"frames": 991},
            "seed_point": {"name": "adv-texture-l2-r0.40", "level": 2, "radius": 0.4}, "points": points,
            "scores": scores, "sentences": {"fpointnet-v1-lite": "fpointnet-v1-lite: <b>none</b> does."},
            "provenance": {"host": {"platform": {"cpu": "test", "cpu_count": 2}}}}


@pytest.fixture()
def sweep_dir(tmp_path: Path) -> Path:
    d = tmp_path / "sweep"
    d.mkdir()
    (d / "sweep.json").write_text(json.dumps(_sweep_doc()), encoding="utf-8")
    return d


def test_the_sweep_section_in_markdown_and_html(sweep_dir, tmp_path):
    out = tmp_path / "report"
    assert main(["report", "--sweep", str(sweep_dir), "--out", str(out)]) == 0
    md = (out / "leaderboard.md").read_text(encoding="utf-8")
    assert "## Dose–response sweep: adv-texture against fpointnet-v1-lite (25 frames)" in md
    figs = sorted(p.name for p in (out / "figures").iterdir())
    assert figs == ["sweep_sweep.png"] and f"(figures/{figs[0]})" in md
    assert "adv-texture-l2-r0.40 ★" in md and "<b>" not in md  # the seed's point marked; strings inert
    html = (out / "leaderboard.html").read_text(encoding="utf-8")
    assert 'id="sweep-0"' in html and "&lt;b&gt;none&lt;/b&gt;" in html and "<b>none</b>" not in html


def test_a_bad_sweep_file_is_refused(tmp_path, capsys):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "sweep.json").write_text(json.dumps({"format": "x"}), encoding="utf-8")
    assert main(["report", "--sweep", str(bad), "--out", str(tmp_path / "r")]) == 2
    assert "sweep.json" in capsys.readouterr().err and not (tmp_path / "r").exists()


def test_the_sweep_section_in_headless_chromium(sweep_dir, tmp_path):
    out = tmp_path / "report"
    assert main(["report", "--sweep", str(sweep_dir), "--out", str(out)]) == 0
    rows = _sweep_doc()["scores"]
    with chromium_page(width=1280, height=1000) as (page, errors):
        page.goto((out / "leaderboard.html").as_uri())
        page.wait_for_load_state("load")
        assert page.evaluate("document.documentElement.scrollWidth") <= 1280
        section = page.locator("#sweep-0")
        assert section.is_visible()
        img = section.locator("img")
        assert img.count() == 1
        img.scroll_into_view_if_needed()
        box = img.bounding_box()
        assert img.is_visible() and box and box["width"] > 600 and box["height"] > 300
        assert img.evaluate("e => e.complete && e.naturalWidth > 0")
        assert page.locator("#sweep-table-0 tbody tr").count() == len(rows)
        # sorting by the relative drop orders the rows as the document's numbers do
        page.locator('#sweep-table-0 th[data-key="relative_drop"]').click()
        names = page.eval_on_selector_all("#sweep-table-0 tbody tr td:nth-child(3)", "ts => ts.map(t => t.innerText)")
        want = [r["name"] + (" ★" if r["seed_point"] else "") for r in sorted(rows, key=lambda r: r["relative_drop"])]
        assert names == want
        shot = tmp_path / "sweep.png"
        section.screenshot(path=str(shot))
    assert errors == []
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copyfile(shot, ARTIFACTS / "report-sweep.png")

"""``robustbench3d report``'s worst case (victims ranked by their worst attacked headline AP, controls excluded,
unequal attack sets flagged, ties and missing cells named) and its transfer matrix over every attack object by
every victim ("not run" where there is no cell, the training victim highlighted), on a hand-made run.

The run: five victims (``lite``, its twin ``lite-onnx``, a LiDAR-only ``pp``, ``cluster`` and ``broken``, whose
cells all failed), the controls (``benign-sphere``, ``random-shape`` and ``benign-sphere-r0.20``, a control by its
object's ``made_by``), objects trained against ``lite`` (``adv-texture``, ``adv-object``) and against ``pp``
(``pp-shape``, as ``attack train --victim pp`` records it), an object file without a training victim
(``file-obj``) and, with GT proposals only, an object trained against ``fpointnet-v1``, a victim not in the run.
Every expected value below is worked out by hand from the AP table :data:`BEV` (Car BEV R40 moderate, %).
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from html.parser import HTMLParser
from pathlib import Path

import pytest
from browser import chromium_page
from cell_builders import hand_provenance

from robustbench3d.cli import main
from robustbench3d.report import data as rdata
from robustbench3d.results import validate_summary

ARTIFACTS = Path(__file__).resolve().parents[2] / ".pytest-artifacts"
DIFFS, RECALLS, SHA = ("easy", "moderate", "hard"), ("R40", "R11"), "ef" * 32
VICTIMS = ("lite", "lite-onnx", "pp", "cluster", "broken")
#: Attack -> (its object's made_by, or None for the clean cell).
OBJECTS = {
    "none": None,
    "benign-sphere": {"attack": "benign-sphere"},
    "random-shape": {"attack": "random-shape", "seed": 0},
    "benign-sphere-r0.20": {"attack": "benign-sphere", "radius": 0.2},
    "adv-texture": {"attack": "adv-texture", "victim": {"name": "lite", "weights_sha256": None, "kwargs": {}}},
    "adv-object": {"attack": "adv-object", "victim": {"name": "lite", "weights_sha256": None, "kwargs": {}}},
    "pp-shape": {"attack": "adv-shape", "victim": {"name": "pp", "weights_sha256": None, "kwargs": {}}},
    "file-obj": {"note": "made by hand"},
    "v1-obj": {"attack": "adv-object", "victim": {"name": "fpointnet-v1"}},
}
ATTACKS = ("adv-texture", "adv-object", "pp-shape", "file-obj")  # the attack objects run with detector proposals
#: Car BEV R40 moderate AP (%) of each (victim, attack) cell with detector proposals; absent: not run.
BEV = {
    "lite": {"none": 80.0, "benign-sphere": 79.0, "random-shape": 78.0, "adv-texture": 50.0, "adv-object": 60.0,
             "pp-shape": 75.0, "file-obj": 70.0},
    "lite-onnx": {"none": 80.0, "benign-sphere": 79.5, "adv-texture": 55.0, "adv-object": 58.0, "file-obj": 72.0},
    "pp": {"none": 70.0, "random-shape": 69.0, "adv-texture": 68.0, "adv-object": 67.0, "pp-shape": 65.0,
           "file-obj": 69.0},
    "cluster": {"none": 75.0, "benign-sphere": 10.0, "benign-sphere-r0.20": 5.0, "adv-texture": 65.0,
                "adv-object": 65.0, "pp-shape": 70.0, "file-obj": 66.0},
}
#: GT proposals: lite only.
BEV_GT = {"lite": {"none": 90.0, "adv-texture": 85.0, "v1-obj": 88.0}}
#: (victim, attack) -> the interval the run recorded of the drop, points (others: none recorded).
DROP_CI = {("lite", "adv-texture"): (24.5, 35.25)}
AP_CI = {("lite", "adv-texture"): (41.0, 58.5)}


def fingerprint(name: str) -> str:
    return hashlib.sha256(name.encode()).hexdigest()


def _table(value: float) -> dict:
    return {"Car": {m: {r: {d: value - 3.0 * (m == "3d") for d in DIFFS} for r in RECALLS}
                    for m in ("bev", "3d")}}


def make_cell(victim: str, attack: str, proposals: str, bev: float | None, clean: float | None,
              status: str = "ok", reason: str | None = None) -> dict:
    """A schema-valid cell whose Car BEV AP is ``bev`` at every recall and difficulty; an attacked ``ok`` cell with a
    ``clean`` AP carries the attack effect against it (drop = clean - bev)."""
    name = f"{victim}+{attack}+{proposals}"
    prov = hand_provenance(victim, attack, proposals, fingerprint(name))
    made_by = OBJECTS[attack]
    if made_by is not None:
        prov["config"]["attack"]["object"] = {"object": {"ply_sha256": fingerprint(attack), "made_by": made_by}}
    metrics = None
    if status == "ok":
        metrics = {**_table(bev), "meta": {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent",
                                           "frames": 12, "classes": ["Car"], "metrics": ["bev", "3d"],
                                           "min_overlap": {"Car": {"bev": 0.7, "3d": 0.7}}}}
    cell = {"schema_version": 1, "victim": victim, "attack": attack, "proposals": proposals, "status": status,
            "reason": reason, "dataset": {"root": "/d", "split": "val", "frames": 12, "split_frames": 40,
                                          "sha256": SHA, "embedded": None, "manifest": None},
            "metrics": metrics, "provenance": prov}
    if (victim, attack) in AP_CI and proposals == "detector":
        meta = {"method": "percentile bootstrap", "statistic": "ap", "level": 0.95, "resamples": 100, "seed": 0,
                "frames": 12, "rng": "numpy"}
        cell["metrics_ci"] = {"meta": meta, "Car": {"bev": {"R40": {"moderate": list(AP_CI[victim, attack])}}}}
    if status == "ok" and attack != "none" and clean is not None:
        effect = {"clean_cell": f"{victim}+none+{proposals}", "clean_fingerprint": fingerprint(f"{victim}+none"),
                  "clean": _table(clean), "drop": _table(clean - bev),
                  "relative_drop": _table((clean - bev) / clean),
                  "success": {"class": "Car", "metric": "bev", "iou": 0.7, "difficulty": "moderate",
                              "score_threshold": 0.5, "clean_matched": 10, "attacked_missed": 1, "rate": 0.1}}
        if (victim, attack) in DROP_CI and proposals == "detector":
            effect["drop_ci"] = {"meta": {"method": "paired percentile bootstrap", "statistic": "drop",
                                          "level": 0.95, "resamples": 100, "seed": 0, "frames": 12, "rng": "numpy"},
                                 "Car": {"bev": {"R40": {"moderate": list(DROP_CI[victim, attack])}}}}
        cell["attack_effect"] = effect
    return cell


def all_cells() -> list[dict]:
    cells = []
    for victim, aps in BEV.items():
        cells += [make_cell(victim, a, "detector", ap, aps["none"]) for a, ap in aps.items()]
    cells += [make_cell("broken", "none", "detector", None, None, "error", "weights missing")]
    cells += [make_cell("broken", a, "detector", None, None, "skipped", "no clean cell ran") for a in ATTACKS]
    for victim, aps in BEV_GT.items():
        cells += [make_cell(victim, a, "gt", ap, aps["none"]) for a, ap in aps.items()]
    return cells


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """The hand-made run directory: ``summary.json`` holding :func:`all_cells` (schema-checked)."""
    root = tmp_path_factory.mktemp("worst") / "run"
    cells = all_cells()
    validate_summary(cells)
    root.mkdir()
    (root / "summary.json").write_text(json.dumps(cells), encoding="utf-8")
    return root


@pytest.fixture(scope="module")
def report(run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("worst_report") / "rep"
    assert main(["report", str(run), "--out", str(out), "--scenes", "0"]) == 0
    return out


def _section(run: Path) -> rdata.Section:
    (sec,) = rdata.sections(rdata.read_runs([run]))
    return sec


def worst_cases(section: rdata.Section) -> list:
    from robustbench3d.report.worst import worst_cases as of_section  # imported here: each test fails on its own

    return of_section(section)


# ------------------------------------------------------------------------- the ranking on the data layer

def test_worst_case_ranking_by_hand(run):
    det, gt = worst_cases(_section(run))
    assert det.proposals == "detector" and det.objects == ATTACKS
    # by hand from BEV: cluster's worst attack 65 (adv-texture and adv-object tie; its controls at 10 and 5 are no
    # attacks), pp's 65 (pp-shape), lite-onnx's 55 (pp-shape not run), lite's 50; broken has no AP at all
    got = [(r.victim, r.rank, r.tied, r.worst_ap, r.by) for r in det.rows]
    assert got == [("cluster", 1, True, 65.0, ("adv-texture", "adv-object")), ("pp", 1, True, 65.0, ("pp-shape",)),
                   ("lite-onnx", 3, False, 55.0, ("adv-texture",)), ("lite", 4, False, 50.0, ("adv-texture",)),
                   ("broken", None, False, None, ())]
    lite = det.rows[3]
    assert (lite.clean, lite.drop, lite.relative_drop) == (80.0, 30.0, 30.0 / 80.0)
    assert lite.drop_ci == (24.5, 35.25) and lite.worst_ci == (41.0, 58.5)
    assert lite.evaluated == ATTACKS and lite.missing == () and not lite.flagged
    assert lite.controls == (("benign-sphere", 79.0, "ok"), ("random-shape", 78.0, "ok"))
    cluster = det.rows[0]
    assert cluster.controls == (("benign-sphere", 10.0, "ok"), ("benign-sphere-r0.20", 5.0, "ok"))
    assert cluster.drop == 10.0 and cluster.drop_ci is None and cluster.drop_note == ""
    # every missing number says why
    broken = det.rows[4]
    assert broken.clean is None and broken.clean_note == "clean cell error"
    assert broken.drop is None and broken.drop_note == "no attack object evaluated"
    assert broken.missing == tuple((a, "skipped") for a in ATTACKS)
    assert det.rows[1].controls == (("random-shape", 69.0, "ok"),)
    # GT proposals: their own table, lite against the two objects run with them
    assert gt.proposals == "gt" and gt.objects == ("adv-texture", "v1-obj")
    assert [(r.victim, r.rank, r.worst_ap, r.by, r.evaluated) for r in gt.rows] == [
        ("lite", 1, 85.0, ("adv-texture",), ("adv-texture", "v1-obj"))]


def test_unequal_attack_sets_are_flagged(run):
    det, gt = worst_cases(_section(run))
    flagged = {r.victim: r.missing for r in det.rows if r.flagged}
    assert flagged == {"lite-onnx": (("pp-shape", "not run"),), "broken": tuple((a, "skipped") for a in ATTACKS)}
    line = det.unequal
    assert line.startswith("Not comparable as a ranking: lite-onnx (3 of 4), broken (0 of 4) were evaluated")
    assert "\n" not in line and gt.unequal == ""


def test_controls_are_never_the_worst_case(run):
    """Without its attack objects a victim has no worst case, however low its controls."""
    only_controls = [c for c in all_cells() if c["victim"] == "cluster" and c["attack"] not in ATTACKS]
    sec = rdata.Section(rdata.comparability_key(only_controls[0]),
                        [rdata.RunCell(run, i, c) for i, c in enumerate(only_controls)])
    assert worst_cases(sec) == []
    assert {rdata.role(c) for c in only_controls} == {"clean", "control"}


# ------------------------------------------------------------------------- the transfer matrix

def test_transfer_matrix_covers_every_object_and_victim(run):
    det, gt = rdata.transfer_grids(rc.cell for rc in _section(run).cells)
    assert det.victims == gt.victims == VICTIMS
    assert [(r.object, r.trained_against) for r in det.rows] == [
        ("adv-texture", "lite"), ("adv-object", "lite"), ("pp-shape", "pp"), ("v1-obj", "fpointnet-v1"),
        ("file-obj", None)]
    assert det.rows == gt.rows
    by_hand = {  # relative drop (%) from BEV, or why there is none
        ("pp-shape", "lite-onnx"): "not run", ("v1-obj", "lite"): "not run", ("adv-texture", "broken"): "skipped",
        ("pp-shape", "pp"): f"{100 * 5 / 70:.1f}", ("adv-texture", "cluster"): f"{100 * 10 / 75:.1f}",
        ("file-obj", "lite"): f"{100 * 10 / 80:.1f}"}
    for (obj, victim), text in by_hand.items():
        row = next(r for r in det.rows if r.object == obj)
        assert det.entry(row, victim).text == text, (obj, victim)
    white = {(r.object, v) for r in det.rows for v in det.victims if det.entry(r, v).white_box}
    assert white == {("adv-texture", "lite"), ("adv-object", "lite"), ("pp-shape", "pp")}
    row = next(r for r in gt.rows if r.object == "v1-obj")
    assert gt.entry(row, "lite").text == f"{100 * 2 / 90:.1f}" and gt.entry(row, "pp").text == "not run"
    m = rdata.transfer_matrix([rc.cell for rc in _section(run).cells], "detector")
    assert m.shape == (5, 5) and m.loc[("pp", "pp-shape"), "pp"] == pytest.approx(5 / 70)


# ------------------------------------------------------------------------- the pages

class Tables(HTMLParser):
    """Every ``table.wc`` and ``table.tm``: id -> rows, each (row attributes, [(cell attributes, text)])."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.tables: dict[str, list[tuple[dict, list[tuple[dict, str]]]]] = {}
        self.current = ""
        self.cell: list | None = None

    def handle_starttag(self, tag, attrs):
        a = {k: v or "" for k, v in attrs}
        if tag == "table" and a.get("class") in ("wc", "tm"):
            self.current = a["id"]
            self.tables[self.current] = []
        elif self.current and tag == "tr":
            self.tables[self.current].append((a, []))
        elif self.current and tag in ("td", "th") and self.tables[self.current]:
            self.cell = [a, ""]
            self.tables[self.current][-1][1].append(self.cell)

    def handle_endtag(self, tag):
        if tag == "table":
            self.current = ""
        if tag in ("td", "th"):
            self.cell = None

    def handle_data(self, data):
        if self.cell is not None:
            self.cell[1] += data


def _tables(report: Path) -> dict:
    p = Tables()
    p.feed((report / "leaderboard.html").read_text(encoding="utf-8"))
    return p.tables


def test_worst_case_and_transfer_in_the_page_and_markdown(report):
    tables = _tables(report)
    det = tables["wc-0-0"]
    body = [(a, cells) for a, cells in det if "data-victim" in a]
    assert [a["data-victim"] for a, _ in body] == ["cluster", "pp", "lite-onnx", "lite", "broken"]
    assert [cells[0][1] for _, cells in body] == ["1=", "1=", "3", "4", "unranked"]
    assert [a.get("class", "") for a, _ in body] == ["", "", "flagged", "", "flagged"]
    lite = [t for _, t in body[3][1]]
    assert lite[2:7] == ["80.00", "50.00[41.00, 58.50]", "adv-texture", f"{100 * 30 / 80:.1f}",
                         "+30.00[+24.50, +35.25]"]
    assert body[0][1][4][1] == "adv-texture = adv-object (tie)"
    assert body[2][1][7][1] == "3 of 4 ⚑not evaluated: pp-shape (not run)"
    assert body[0][1][8][1] == "benign-sphere 10.00; benign-sphere-r0.20 5.00"
    assert [t for _, t in body[4][1][2:4]] == ["clean cell error", "none evaluated"]
    # the transfer table: every object by every victim, not run said, the training victim highlighted
    tm = tables["tm-0-0"]
    head = [t for _, t in tm[0][1]]
    assert head == ["trained against · object", *VICTIMS]
    rows = {a["data-object"]: cells for a, cells in tm[1:]}
    assert set(rows) == {"adv-texture", "adv-object", "pp-shape", "v1-obj", "file-obj"}
    assert rows["file-obj"][0][1] == "(object file) · file-obj"
    assert rows["v1-obj"][0][1] == "fpointnet-v1 · v1-objtrained against a victim not evaluated here"
    assert [t for _, t in rows["v1-obj"][1:]] == ["not run"] * 5
    assert rows["pp-shape"][2] == [{"class": "nr", "data-victim": "lite-onnx",
                                    "title": "lite-onnx+pp-shape+detector: not run"}, "not run"]
    assert rows["pp-shape"][3][0]["class"] == "num wb" and rows["pp-shape"][3][1] == f"{100 * 5 / 70:.1f}"
    assert sum("wb" in a["class"].split() for cells in rows.values() for a, _ in cells[1:]) == 3
    assert all(t for cells in rows.values() for _, t in cells)  # no blank entry
    md = (report / "leaderboard.md").read_text(encoding="utf-8")
    assert "### Worst case: victims ranked by their worst attacked AP" in md
    ranked = [[c.strip() for c in line.split("|")[1:3]] for line in md.splitlines()
              if line.startswith("| ") and line.split("|")[2].strip() in VICTIMS and "·" not in line]
    assert ranked == [["1=", "cluster"], ["1=", "pp"], ["3", "lite-onnx"], ["4", "lite"], ["unranked", "broken"],
                      ["1", "lite"]]  # detector, then GT proposals
    assert "⚑ Not comparable as a ranking: lite-onnx (3 of 4), broken (0 of 4)" in md
    assert f"**{100 * 5 / 70:.1f}**" in md and md.count("not run") >= 9


HOSTILE = "<img src=x onerror=alert(1)> a|b *c* [l](javascript:alert(2))"


def test_a_hostile_training_victim_name_is_inert(tmp_path):
    """The training victim comes from an object's sidecar, any string: shown as given, never markup."""
    cells = copy.deepcopy(all_cells())
    for c in cells:
        if c["attack"] == "pp-shape":
            c["provenance"]["config"]["attack"]["object"]["object"]["made_by"]["victim"]["name"] = HOSTILE
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps(cells), encoding="utf-8")
    assert main(["report", str(run), "--out", str(tmp_path / "rep"), "--scenes", "0"]) == 0
    page = (tmp_path / "rep" / "leaderboard.html").read_text(encoding="utf-8")
    md = (tmp_path / "rep" / "leaderboard.md").read_text(encoding="utf-8")
    assert "<img src=x" not in page and "<img src=x" not in md
    row = next(cells for a, cells in _tables(tmp_path / "rep")["tm-0-0"] if a.get("data-object") == "pp-shape")
    assert row[0][1].startswith(f"{HOSTILE} · pp-shape")
    markdown_it = pytest.importorskip("markdown_it")
    rendered = markdown_it.MarkdownIt("commonmark").enable("table").render(md)
    transfer = rendered.split("Transfer matrix")[1].split("<table>")[1].split("</table>")[0]
    head, *rows = transfer.split("<tr>")[1:]
    assert all(r.count("<td>") == head.count("<th>") == len(VICTIMS) + 1 for r in rows)  # the | splits no cell
    assert "<a " not in rendered and "<img src=x" not in rendered


def test_worst_case_section_in_headless_chromium(report, tmp_path):
    with chromium_page(width=1280, height=1000) as (page, errors):
        page.goto((report / "leaderboard.html").as_uri())
        page.wait_for_load_state("load")
        assert page.evaluate("document.documentElement.scrollWidth") <= page.evaluate("window.innerWidth") == 1280
        block = page.locator("#wc-block-0")
        block.scroll_into_view_if_needed()
        assert block.is_visible()
        for table in ("#wc-0-0", "#wc-0-1", "#tm-0-0", "#tm-0-1"):  # each fits its box: no sideways scroll
            sw, cw = page.locator(table).evaluate("t => [t.scrollWidth, t.parentElement.clientWidth]")
            assert sw <= cw, table
        ranks = page.eval_on_selector_all("#wc-0-0 tbody tr", "rs => rs.map(r => r.dataset.victim)")
        assert ranks == ["cluster", "pp", "lite-onnx", "lite", "broken"]
        # the flagged rows stand out and the line saying why is shown
        colours = page.eval_on_selector_all("#wc-0-0 tbody tr td:first-child",
                                            "ts => ts.map(t => getComputedStyle(t).backgroundColor)")
        assert colours[2] == colours[4] != colours[3]
        assert page.locator("#wc-block-0 p.unequal").first.is_visible()
        # the white-box entry is outlined, a transfer entry is not
        wb = page.locator('#tm-0-0 tr[data-object="pp-shape"] td[data-victim="pp"]')
        other = page.locator('#tm-0-0 tr[data-object="pp-shape"] td[data-victim="cluster"]')
        assert wb.evaluate("t => getComputedStyle(t).boxShadow") != "none"
        assert other.evaluate("t => getComputedStyle(t).boxShadow") == "none"
        # the worst cell's provenance is one click away
        link = page.locator('#wc-0-0 tr[data-victim="lite"] a.prov')
        link.click()
        assert page.locator(link.get_attribute("href")).evaluate("d => d.open") is True
        shot = tmp_path / "worst.png"
        block.screenshot(path=str(shot))
    assert errors == []
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copyfile(shot, ARTIFACTS / "report-worst-case.png")

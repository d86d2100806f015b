"""``robustbench3d report``'s Table 1 block (the seed paper's Table 1 beside each victim's measured rows), its
notes on the cells merged or left out, and the page's fit at 1280 px in headless Chromium, on hand-made runs.

References are independent of the code under test: the paper's numbers are the issue's constants, the
mapping of its rows to cells is the issue's (clean: attack ``none`` with any proposals; LiDAR-only:
``adv-shape`` with GT 2D boxes; image-only: ``adv-texture`` and LiDAR+image: ``adv-object`` with the
victim's 2D detector), and every measured number is read from the ``summary.json`` written here.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

import pytest
from browser import chromium_page
from cell_builders import hand_provenance

from robustbench3d.cli import main
from robustbench3d.results import validate_summary

ARTIFACTS = Path(__file__).resolve().parents[2] / ".pytest-artifacts"
DIFFS = ("easy", "moderate", "hard")
RECALLS = ("R40", "R11")
ATTACKS = ("none", "benign-sphere", "random-shape", "adv-shape", "adv-texture", "adv-object")
#: The issue's Table 1: Car BEV AP @ 0.7, easy / moderate / hard.
PAPER = {"clean": (85.7, 83.6, 76.2), "LiDAR-only": (37.4, 37.8, 39.1), "image-only": (51.9, 36.0, 31.5),
         "LiDAR+image": (27.5, 22.7, 19.2)}
#: The issue's map of paper rows to (attack, proposals); clean: every proposal source.
ROW_OF = {("none", "detector"): "clean", ("none", "gt"): "clean", ("adv-shape", "gt"): "LiDAR-only",
          ("adv-texture", "detector"): "image-only", ("adv-object", "detector"): "LiDAR+image"}
GT_LABEL = "GT 2D boxes (object outside the frustum)"
SHA = "cd" * 32
CI_META = {"method": "percentile bootstrap over frames", "statistic": "AP", "level": 0.95, "resamples": 1000,
           "seed": 0, "frames": 12, "rng": "numpy"}
FP, LC, LONG = "fp", "lc", "pointpillars-very-long-victim-name-v2"


def fingerprint(name: str) -> str:
    return hashlib.sha256(name.encode()).hexdigest()


def ap(victim: str, attack: str, proposals: str, metric: str, recall: str, d: str) -> float:
    """A made-up AP (percent) with many decimals, different for every argument."""
    return (93.123456789 - 9.5 * ATTACKS.index(attack) - 4.25 * DIFFS.index(d) - 1.75 * (recall == "R11")
            - 3.0 * (proposals == "gt") - 2.0 * (metric == "3d") + 0.37 * (len(victim) % 5))


def _table(f) -> dict:
    return {"Car": {m: {r: {d: f(m, r, d) for d in DIFFS} for r in RECALLS} for m in ("bev", "3d")}}


def make_cell(victim: str, attack: str, proposals: str, *, ci: bool = True, reason: str | None = None,
              shift: float = 0.0, effect: bool = True) -> dict:
    """A schema-valid summary cell; ``reason``: a skipped cell; attacked ``ok`` cells carry an attack effect
    against the clean cell of the same victim and proposals (as :func:`ap` makes it) unless ``effect`` is
    False (no clean cell to compare with)."""
    name = f"{victim}+{attack}+{proposals}"
    ok = reason is None
    metrics = None
    if ok:
        metrics = _table(lambda m, r, d: ap(victim, attack, proposals, m, r, d) + shift)
        metrics["meta"] = {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent", "frames": 12,
                           "classes": ["Car"], "metrics": ["bev", "3d"], "min_overlap": {"Car": {"bev": 0.7,
                                                                                                "3d": 0.7}}}
    cell = {
        "schema_version": 1, "victim": victim, "attack": attack, "proposals": proposals,
        "status": "ok" if ok else "skipped", "reason": reason,
        "dataset": {"root": "/d", "split": "val", "frames": 12, "split_frames": 40, "sha256": SHA, "embedded": None,
                    "manifest": None},
        "metrics": metrics,
        "provenance": hand_provenance(victim, attack, proposals, fingerprint(name)),
    }
    if ok and ci:
        cell["metrics_ci"] = {"meta": CI_META, "Car": {"bev": {r: {d: [metrics["Car"]["bev"][r][d] - 4.25,
                                                                      metrics["Car"]["bev"][r][d] + 2.5]
                                                                  for d in DIFFS} for r in RECALLS}}}
    if ok and attack != "none" and effect:
        def clean(m, r, d):
            return ap(victim, "none", proposals, m, r, d)

        def drop(m, r, d):
            return clean(m, r, d) - metrics["Car"][m][r][d]

        missed = ATTACKS.index(attack)
        cell["attack_effect"] = {
            "clean_cell": f"{victim}+none+{proposals}", "clean_fingerprint": fingerprint(f"{victim}+none+{proposals}"),
            "clean": _table(clean), "drop": _table(drop),
            "relative_drop": _table(lambda m, r, d: drop(m, r, d) / clean(m, r, d)),
            "success": {"class": "Car", "metric": "bev", "iou": 0.7, "difficulty": "moderate",
                        "score_threshold": 0.5, "clean_matched": 16, "attacked_missed": missed, "rate": missed / 16}}
    if victim == FP and ok:
        cell["flags"] = [{"code": "partial-split", "message": "evaluated on 12 of the 40 frames of split 'val'"}]
    return cell


def write_run(path: Path, cells: list[dict]) -> Path:
    validate_summary([{k: v for k, v in c.items() if k != "flags"} for c in cells])
    path.mkdir(parents=True)
    (path / "summary.json").write_text(json.dumps(cells), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    """Run A: victim fp's whole grid (six attacks, detector and gt proposals), victim lc's clean cells (gt
    skipped) and a control. Run B: victim LONG's clean and adv-texture cells (no intervals), fp's adv-object
    and clean detector cells again (identical), fp's adv-texture gt cell with the same configuration but
    other numbers, and LONG's random-shape cell with gt proposals, which has no clean cell to compare with."""
    root = tmp_path_factory.mktemp("table1")
    a = [make_cell(FP, att, p) for att in ATTACKS for p in ("detector", "gt")]
    a += [make_cell(LC, "none", "detector"), make_cell(LC, "none", "gt", reason="lc supports detector proposals only"),
          make_cell(LC, "random-shape", "detector")]
    b = [make_cell(LONG, "none", "detector", ci=False), make_cell(LONG, "adv-texture", "detector", ci=False),
         make_cell(FP, "adv-object", "detector"), make_cell(FP, "none", "detector"),
         make_cell(FP, "adv-texture", "gt", shift=-1.0), make_cell(LONG, "random-shape", "gt", ci=False, effect=False)]
    return write_run(root / "runA", a), write_run(root / "runB", b)


@pytest.fixture(scope="module")
def report(runs, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("table1_report") / "rep"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["report", *map(str, runs), "--out", str(out), "--scenes", "0"]) == 0
    return out, buf.getvalue()


class Block(HTMLParser):
    """The Table 1 block ``#t1-0``: per group (``data-t1-row``) its rows: (``data-t1-cell`` or "" for the
    paper's, the td attributes, the row's text)."""

    def __init__(self, table_id: str = "t1-0") -> None:
        super().__init__(convert_charrefs=True)
        self.table_id, self.inside, self.depth = table_id, False, 0
        self.groups: dict[str, list[tuple[str, list[dict[str, str]], list[str]]]] = {}
        self.group = ""

    def handle_starttag(self, tag, attrs):
        a = {k: v or "" for k, v in attrs}
        if tag == "table" and a.get("id") == self.table_id:
            self.inside = True
        if not self.inside:
            return
        if tag == "tbody":
            self.group = a["data-t1-row"]
            self.groups[self.group] = []
        elif tag == "tr" and self.group:
            self.groups[self.group].append((a.get("data-t1-cell", ""), [], []))
        elif tag == "td" and self.group:
            self.groups[self.group][-1][1].append(a)

    def handle_endtag(self, tag):
        if tag == "table" and self.inside:
            self.inside = False
            self.group = ""

    def handle_data(self, data):
        if self.inside and self.group and self.groups[self.group]:
            self.groups[self.group][-1][2].append(data)


def block(page: str, table_id: str = "t1-0") -> Block:
    p = Block(table_id)
    p.feed(page)
    return p


def _summary(runs: tuple[Path, Path]) -> dict[str, dict]:
    """The cells the report shows: by name, the first run's where one is given twice."""
    return {name: cell for name, (cell, _) in _sources(runs).items()}


def _sources(runs: tuple[Path, Path]) -> dict[str, tuple[dict, str]]:
    """By name: the cell the report shows and where it comes from (``RUN/summary.json[i]``)."""
    out: dict[str, tuple[dict, str]] = {}
    for run in runs:
        for i, c in enumerate(json.loads((run / "summary.json").read_text())):
            out.setdefault(f"{c['victim']}+{c['attack']}+{c['proposals']}", (c, f"{run / 'summary.json'}[{i}]"))
    return out


def _unescaped(md: str) -> str:
    """Markdown text with its backslash escapes undone (what a renderer shows)."""
    return re.sub(r"\\(.)", r"\1", md)


def _num(a: dict[str, str], key: str) -> float | None:
    return None if a.get(key, "") == "" else float(a[key])


def test_table1_block_numbers_equal_the_paper_and_the_summary(runs, report):
    out, _ = report
    cells = _summary(runs)
    page = block((out / "leaderboard.html").read_text(encoding="utf-8"))
    assert list(page.groups) == list(PAPER)
    for label, rows in page.groups.items():
        paper_cell, paper_tds, _ = rows[0]
        assert paper_cell == ""  # the paper's line first
        expect_m = PAPER[label][1]
        for d, td in enumerate(paper_tds[1:4]):
            assert _num(td, "data-r40") == _num(td, "data-r11") == PAPER[label][d]
        clean_m, rel, asr = paper_tds[4:7]
        if label == "clean":
            assert _num(clean_m, "data-r40") is None and _num(rel, "data-r40") is None
        else:  # the paper's relative drop at moderate against its clean row
            assert _num(clean_m, "data-r40") == PAPER["clean"][1]
            assert _num(rel, "data-r40") == pytest.approx((PAPER["clean"][1] - expect_m) / PAPER["clean"][1])
        assert _num(asr, "data-r40") is None
        # exactly the cells of this paper row, every victim's, in the section
        expect = {n for n, c in cells.items() if ROW_OF.get((c["attack"], c["proposals"])) == label}
        assert {r[0] for r in rows[1:]} == expect and len(rows) == len(expect) + 1
        for name, tds, text in rows[1:]:
            cell = cells[name]
            if cell["proposals"] == "gt":
                assert GT_LABEL in "".join(text)
            if cell["status"] != "ok":
                assert "".join(text).count(cell["reason"]) == 1 and len(tds) == 2  # who, and one "no AP" cell
                continue
            bev = cell["metrics"]["Car"]["bev"]
            for d, td in zip(DIFFS, tds[1:4], strict=True):
                for recall in RECALLS:
                    assert _num(td, f"data-{recall.lower()}") == bev[recall][d]
                    ci = cell.get("metrics_ci", {}).get("Car", {}).get("bev", {}).get(recall, {}).get(d)
                    got = td.get(f"data-ci{recall[1:]}", "")
                    assert (got == "" if ci is None else [float(x) for x in got.split()] == ci)
            effect = cell.get("attack_effect")
            clean_td, rel_td, asr_td = tds[4:7]
            for recall in RECALLS:
                key = f"data-{recall.lower()}"
                if effect is None:
                    assert _num(clean_td, key) is _num(rel_td, key) is _num(asr_td, key) is None
                    continue
                assert _num(clean_td, key) == effect["clean"]["Car"]["bev"][recall]["moderate"]
                assert _num(rel_td, key) == effect["relative_drop"]["Car"]["bev"][recall]["moderate"]
                assert _num(asr_td, key) == effect["success"]["rate"]


def _md_table1(md: str) -> list[list[str]]:
    """The cells of the markdown's first Table 1 table (between its heading and the next heading)."""
    part = md.split("### Seed paper Table 1 beside the measured rows", 1)[1].split("\n### ", 1)[0]
    lines = [ln for ln in part.splitlines() if ln.startswith("|")][2:]
    return [[c.strip() for c in ln.strip("|").split(" | ")] for ln in lines]


def test_table1_block_in_the_markdown(runs, report):
    out, _ = report
    sources = _sources(runs)
    rows = _md_table1((out / "leaderboard.md").read_text(encoding="utf-8"))
    paper = [r for r in rows if r[1] == "seed paper"]
    assert [r[0].split("**")[1] for r in paper] == list(PAPER)
    assert [tuple(map(float, r[2:5])) for r in paper] == list(PAPER.values())
    measured = {_unescaped(r[-1].strip("`")): r for r in rows if r[1] != "seed paper"}
    expect = {src: cell for cell, src in sources.values() if (cell["attack"], cell["proposals"]) in ROW_OF}
    assert set(measured) == set(expect)
    for src, cell in expect.items():
        row = measured[src]
        assert row[1].startswith(f"{cell['victim']} · ") and (GT_LABEL in _unescaped(row[1])) == (
            cell["proposals"] == "gt")
        if cell["status"] != "ok":
            assert row[2] == f"no AP: skipped: {cell['reason']}"
            continue
        bev = cell["metrics"]["Car"]["bev"]
        for d, text in zip(DIFFS, row[2:5], strict=True):
            ci = cell.get("metrics_ci", {}).get("Car", {}).get("bev", {}).get("R40", {}).get(d)
            interval = "" if ci is None else f" [{ci[0]:.1f}, {ci[1]:.1f}]"
            assert _unescaped(text) == f"{bev['R40'][d]:.2f}{interval} ({bev['R11'][d]:.2f})"
        effect = cell.get("attack_effect")
        rel, asr = row[6], row[7]
        if effect is None:
            assert (rel, asr) == ("– (–)", "–")
        else:
            drop = effect["relative_drop"]["Car"]["bev"]
            assert rel == f"{100 * drop['R40']['moderate']:.1f} ({100 * drop['R11']['moderate']:.1f})"
            assert asr == f"{100 * effect['success']['rate']:.1f}"


def test_cells_merged_or_left_out_are_named_with_their_run_and_why(runs, report):
    out, printed = report
    run_a, run_b = runs
    page = (out / "leaderboard.html").read_text(encoding="utf-8")
    md = (out / "leaderboard.md").read_text(encoding="utf-8")
    b_cells = json.loads((run_b / "summary.json").read_text())
    a_cells = json.loads((run_a / "summary.json").read_text())
    a_index = {f"{c['victim']}+{c['attack']}+{c['proposals']}": i for i, c in enumerate(a_cells)}
    notes = _notes(page, "cell-notes")
    for i, c in enumerate(b_cells):
        name = f"{c['victim']}+{c['attack']}+{c['proposals']}"
        if name not in a_index:
            continue
        same = c == a_cells[a_index[name]]
        (note,) = [n for n in notes if n.startswith(f"{name} ({run_b / 'summary.json'}[{i}]) is left out")]
        assert f"same cell as {run_a / 'summary.json'}[{a_index[name]}]" in note
        assert ("identical results" in note) == same and ("different results" in note) == (not same)
        assert note in _unescaped(md) and f"report: {note}" in printed  # the markdown and the output say it too
    assert sum("is left out: it is the same cell" in n for n in notes) == 3  # exactly run B's three twins
    # the skipped cell: no AP, named with its run and reason
    skipped = a_index["lc+none+gt"]
    (no_ap,) = [n for n in notes if n.startswith("No AP")]
    assert f"lc+none+gt ({run_a / 'summary.json'}[{skipped}]): skipped, lc supports detector proposals only" in no_ap
    # cells of the section that are no row of Table 1: named, with their run
    (outside,) = [n for n in _notes(page, "t1-notes") if n.startswith("Not rows of Table 1")]
    expect_a = [n for n, c in ((f"{c['victim']}+{c['attack']}+{c['proposals']}", c) for c in a_cells)
                if (c["attack"], c["proposals"]) not in ROW_OF]
    assert f"from {run_a}: {', '.join(expect_a)}" in outside
    assert f"from {run_b}: {LONG}+random-shape+gt." in outside  # run B's only cell shown that is no Table 1 row
    # an attacked cell without a clean comparison: no drop, named
    (lone,) = [n for n in notes if n.startswith("No clean cell")]
    assert lone.endswith(f": {LONG}+random-shape+gt ({run_b / 'summary.json'}[5]).")
    # rows of the paper a victim has no cell for, with what fills them
    (absent,) = [n for n in _notes(page, "t1-notes") if n.startswith("No cell for these rows")]
    parts = dict(p.split(": ", 1) for p in absent.split(": ", 1)[1].rstrip(".").split("; "))
    assert set(parts) == {LC, LONG}  # fp has every row
    assert parts[LC] == ("LiDAR-only (--attacks adv-shape --proposals gt), image-only (--attacks adv-texture "
                         "--proposals detector), LiDAR+image (--attacks adv-object --proposals detector)")
    assert parts[LONG] == ("clean (--attacks none --proposals gt), LiDAR-only (--attacks adv-shape --proposals gt), "
                           "LiDAR+image (--attacks adv-object --proposals detector)")
    for n in [no_ap, outside, absent, lone]:
        assert n in _unescaped(md)


def _notes(page: str, cls: str) -> list[str]:
    class Items(HTMLParser):
        def __init__(self):
            super().__init__(convert_charrefs=True)
            self.inside, self.items = False, []

        def handle_starttag(self, tag, attrs):
            if tag == "ul" and cls in (dict(attrs).get("class") or "").split():
                self.inside = True
            elif tag == "li" and self.inside:
                self.items.append("")

        def handle_endtag(self, tag):
            if tag == "ul":
                self.inside = False

        def handle_data(self, data):
            if self.inside and self.items:
                self.items[-1] += data

    p = Items()
    p.feed(page)
    return p.items


def test_a_further_lidar_protocol_is_a_further_lidar_only_row(runs):
    """Issue #33's proposal sources (e.g. ``gt-object``) become LiDAR-only rows with no change to the report."""
    from robustbench3d.report import data as rdata
    from robustbench3d.report.page import html_page
    from robustbench3d.report.view import SectionView
    from robustbench3d.seed_table import PAPER_LIDAR, SeedRow, layout_rows

    assert SeedRow("adv-shape", "adv-shape", "gt-object", PAPER_LIDAR) in layout_rows(["detector", "gt", "gt-object"])
    cells = [make_cell(FP, att, p) for att in ATTACKS for p in ("detector", "gt", "gt-object")]
    section = rdata.Section(rdata.comparability_key(cells[0]),
                            [rdata.RunCell(runs[0], i, c) for i, c in enumerate(cells)])
    page = block(html_page([SectionView(section, rdata.table(section))], "t", [str(runs[0])], []))
    lidar = {name: "".join(text) for name, _, text in page.groups["LiDAR-only"][1:]}
    assert set(lidar) == {f"{FP}+adv-shape+gt", f"{FP}+adv-shape+gt-object"}
    assert GT_LABEL in lidar[f"{FP}+adv-shape+gt"] and "gt-object" in lidar[f"{FP}+adv-shape+gt-object"]
    assert {n for n, _, _ in page.groups["clean"][1:]} == {f"{FP}+none+{p}" for p in ("detector", "gt", "gt-object")}
    assert {n for n, _, _ in page.groups["image-only"][1:]} == {f"{FP}+adv-texture+detector"}


# ---------------------------------------------------------------- the page at 1280 px in headless Chromium

def test_page_fits_1280_px_and_shows_table1(runs, report, tmp_path):
    out, _ = report
    cells = _summary(runs)
    with chromium_page(width=1280, height=900) as (page, errors):
        page.goto((out / "leaderboard.html").as_uri())
        page.wait_for_load_state("load")
        width = page.evaluate("window.innerWidth")
        assert width == 1280
        assert page.evaluate("document.documentElement.scrollWidth") <= width  # no sideways scroll of the page
        # the leaderboard's default columns fit its box, the run column among the hidden ones
        fits = "t => [t.scrollWidth, t.parentElement.clientWidth]"
        sw, cw = page.locator("#lb-0").evaluate(fits)
        assert sw <= cw
        assert not page.locator('#lb-0 th[data-key="run"]').is_visible()
        t1, whole = page.locator("#t1-0"), page.locator("#t1-block-0")  # the table; with heading, legend, notes
        whole.scroll_into_view_if_needed()
        assert t1.is_visible() and whole.is_visible()
        for element in (t1, whole):
            box = element.bounding_box()
            assert box and box["x"] >= 0 and box["x"] + box["width"] <= width
        sw, cw = t1.evaluate(fits)
        assert sw <= cw
        # the R11 toggle switches Table 1's measured numbers, never the paper's
        name = f"{FP}+adv-shape+gt"
        moderate = page.locator(f'#t1-0 tr[data-t1-cell="{name}"] td').nth(2)
        paper = page.locator('#t1-0 tbody[data-t1-row="LiDAR-only"] tr.paper td').nth(2)
        bev = cells[name]["metrics"]["Car"]["bev"]
        assert moderate.inner_text().split()[0] == f"{bev['R40']['moderate']:.2f}"
        shot = tmp_path / "report-table1.png"
        whole.screenshot(path=str(shot))
        page.locator('button[data-recall="R11"]').click()
        assert moderate.inner_text().split()[0] == f"{bev['R11']['moderate']:.2f}"
        assert paper.inner_text() == "37.8"
        page.locator('button[data-recall="R40"]').click()
        # more columns on demand: shown, the table scrolls in its own box, the page still does not
        for box_ in page.locator("input[data-group]").all():
            box_.check()
        assert page.locator('#lb-0 th[data-key="run"]').is_visible()
        assert page.locator('#lb-0 th[data-key="3d_{recall}_moderate"]').is_visible()
        sw, cw = page.locator("#lb-0").evaluate(fits)
        assert sw > cw and page.evaluate("document.documentElement.scrollWidth") <= width
    assert errors == []
    assert shot.read_bytes()[:4] == b"\x89PNG"
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copyfile(shot, ARTIFACTS / "report-table1.png")

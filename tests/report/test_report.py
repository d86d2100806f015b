"""``robustbench3d report``: table numbers equal the summary's (read independently), runs that are not comparable
are separated or refused, the transfer matrix on hand-made cells, and the page in a real headless browser
(no console error, figures visible, sorting, the R40/R11 toggle; a screenshot kept as a test artefact)."""

from __future__ import annotations

import copy
import importlib.util
import json
import math
import shutil
from html.parser import HTMLParser
from pathlib import Path

import pytest
from browser import chromium_page

from robustbench3d.cli import main
from robustbench3d.errors import RobustBenchError
from robustbench3d.report import data as rdata
from robustbench3d.report.page import SectionView, html_page, markdown

ARTIFACTS = Path(__file__).resolve().parents[2] / ".pytest-artifacts"
needs_plugin = pytest.mark.skipif(
    importlib.util.find_spec("rb3d_lidar_cluster") is None,
    reason="example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim",
)


# ------------------------------------- a tiny real run (3 frames; 3 ok cells, 3 skipped: lidar-cluster has no gt)

@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, shared_split) -> Path:
    if importlib.util.find_spec("rb3d_lidar_cluster") is None:
        pytest.skip("example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim")
    root = tmp_path_factory.mktemp("report")
    ds = shared_split(3, seed=5, val_fraction=1.0)
    out = root / "run"
    assert main(["run", "--victims", "lidar-cluster", "--attacks", "none,random-shape,benign-sphere",
                 "--proposals", "detector,gt", "--data", str(ds), "--out", str(out), "--no-progress",
                 "--jobs", "1"]) == 0
    return out


@pytest.fixture(scope="module")
def tiny_report(tiny_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("report_out")
    assert main(["report", str(tiny_run), "--out", str(out), "--scenes", "1"]) == 0
    return out


class Rows(HTMLParser):
    """Each table row's data-cell and its td attributes, in document order."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[tuple[str, list[dict[str, str]]]] = []
        self.heads: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = {k: v or "" for k, v in attrs}
        if tag == "tr" and "data-cell" in a:
            self.rows.append((a["data-cell"], []))
        elif tag == "td" and self.rows:
            self.rows[-1][1].append(a)
        elif tag == "th" and "data-key" in a and len(self.rows) == 0:
            self.heads.append(a["data-key"])


def _parse(html_text: str) -> Rows:
    p = Rows()
    p.feed(html_text)
    return p


def _floats(a: dict[str, str], key: str) -> float:
    return math.nan if a.get(key, "") == "" else float(a[key])


def _same(x: float, y) -> bool:
    return (y is None and math.isnan(x)) or (y is not None and x == y)


@needs_plugin
def test_table_numbers_equal_the_summary(tiny_run, tiny_report):
    summary = json.loads((tiny_run / "summary.json").read_text())
    by_name = {f"{c['victim']}+{c['attack']}+{c['proposals']}": c for c in summary}
    clean = by_name["lidar-cluster+none+detector"]
    page = _parse((tiny_report / "leaderboard.html").read_text(encoding="utf-8"))
    assert [r[0] for r in page.rows] == list(by_name)
    col = {k: i for i, k in enumerate(page.heads)}
    assert sum(c["status"] == "skipped" for c in summary) == 3
    for name, tds in page.rows:
        cell = by_name[name]
        if cell["status"] != "ok":  # no number at all, the status and its reason shown
            assert all(a.get("data-r40", "") == "" and a.get("data-v", "") == "" for a in tds if "class" in a)
            assert {"data-v": "skipped", "title": cell["reason"]} in tds
            continue
        for metric in ("bev", "3d"):
            for d in ("easy", "moderate", "hard"):
                td = tds[col[f"{metric}_{{recall}}_{d}"]]
                for recall in ("R40", "R11"):
                    assert _floats(td, f"data-{recall.lower()}") == cell["metrics"]["Car"][metric][recall][d]
        for recall in ("R40", "R11"):
            att = cell["metrics"]["Car"]["bev"][recall]["moderate"]
            ref = clean["metrics"]["Car"]["bev"][recall]["moderate"]
            drop = _floats(tds[col["drop_{recall}"]], f"data-{recall.lower()}")
            rel = _floats(tds[col["rel_drop_{recall}"]], f"data-{recall.lower()}")
            cln = _floats(tds[col["clean_{recall}"]], f"data-{recall.lower()}")
            if cell is clean:
                assert math.isnan(drop) and math.isnan(rel) and math.isnan(cln)
            else:  # independently: the clean cell's AP minus this cell's
                assert cln == ref and drop == pytest.approx(ref - att, abs=1e-9)
                assert rel == pytest.approx((ref - att) / ref, abs=1e-12)
        if "metrics_ci" in cell:  # intervals recorded by the run are shown as recorded
            for recall in ("R40", "R11"):
                lo, hi = cell["metrics_ci"]["Car"]["bev"][recall]["moderate"]
                td = tds[col["ci_low_{recall}"]]
                assert _floats(td, f"data-{recall.lower()}") == lo
                assert td[f"data-t{recall[1:]}"] == f"[{lo:.2f}, {hi:.2f}]"
        asr = _floats(tds[col["asr"]], "data-v")
        effect = cell.get("attack_effect")
        assert _same(asr, None if effect is None else effect["success"]["rate"])
    # the markdown shows the same numbers (R40, R11 in parentheses) and names each cell's source
    md = (tiny_report / "leaderboard.md").read_text(encoding="utf-8")
    for i, cell in enumerate(summary):
        assert f"summary.json[{i}]`" in md
        if cell["status"] != "ok":
            continue
        bev = cell["metrics"]["Car"]["bev"]
        assert f"{bev['R40']['moderate']:.2f} ({bev['R11']['moderate']:.2f})" in md
        assert f"summary.json[{i}]`" in md
    # every figure written next to the markdown is linked from it, and is a PNG
    figs = sorted((tiny_report / "figures").iterdir())
    assert figs and all(f"figures/{f.name})" in md and f.read_bytes()[:4] == b"\x89PNG" for f in figs)
    assert any("scene" in f.name for f in figs)


def _copy_run(src: Path, dst: Path, edit) -> Path:
    shutil.copytree(src, dst)
    cells = json.loads((dst / "summary.json").read_text())
    for c in cells:
        edit(c)
    (dst / "summary.json").write_text(json.dumps(cells))
    return dst


def _other_sha(c):
    c["dataset"]["sha256"] = "0" * 64
    c["provenance"]["config"]["dataset"]["sha256"] = "0" * 64


def _other_numpy(c):
    c["provenance"]["versions"]["numpy"] = "0.0.1"


def _other_iou(c):
    if c["metrics"]:
        c["metrics"]["meta"]["min_overlap"]["Car"]["bev"] = 0.5


@needs_plugin
@pytest.mark.parametrize(("edit", "field"), [(_other_sha, "dataset.sha256"), (_other_numpy, "versions.numpy"),
                                             (_other_iou, "protocol.iou.Car.bev")])
def test_runs_that_differ_are_separated_or_refused(tiny_run, tmp_path, capsys, edit, field):
    other = _copy_run(tiny_run, tmp_path / "other", edit)
    secs = rdata.sections(rdata.read_runs([tiny_run, other]))
    assert [len(s.cells) for s in secs] == [6, 6] and secs[0].runs == [tiny_run] and secs[1].runs == [other]
    assert secs[0].differs == [] and [d.split(":")[0] for d in secs[1].differs] == [field]
    if edit is _other_sha:  # the page, once: two tables, and why they are apart
        out = tmp_path / "rep"
        assert main(["report", str(tiny_run), str(other), "--out", str(out), "--scenes", "0"]) == 0
        page = (out / "leaderboard.html").read_text(encoding="utf-8")
        assert page.count('<table class="lb"') == 2 and "Kept apart from section 1 because these differ" in page
        assert field in page and field in (out / "leaderboard.md").read_text(encoding="utf-8")
    assert main(["report", str(tiny_run), str(other), "--out", str(tmp_path / "rep2"), "--strict"]) == 2
    err = capsys.readouterr().err
    assert "not comparable" in err and field in err and str(other) in err


@needs_plugin
def test_the_same_cells_twice_count_once_and_conflicting_twins_are_refused(tiny_run, tmp_path):
    twin = _copy_run(tiny_run, tmp_path / "twin", lambda c: None)
    secs = rdata.sections(rdata.read_runs([tiny_run, twin]))
    assert len(secs) == 1 and [c.run for c in secs[0].cells] == [tiny_run] * 6
    # each twin is recorded, the kept cell and the one left out (tests/report/test_report_table1.py: the notes)
    assert [(m.kept.run, m.dropped.run, m.kept.index, m.dropped.index, m.same_results) for m in secs[0].merged] \
        == [(tiny_run, twin, i, i, True) for i in range(6)]

    def refingerprint(c):
        c["provenance"]["fingerprint"] = "f" * 64

    changed = _copy_run(tiny_run, tmp_path / "changed", refingerprint)
    with pytest.raises(RobustBenchError, match="different configurations"):
        rdata.sections(rdata.read_runs([tiny_run, changed]))


def test_bad_run_directories_are_refused(tmp_path, capsys):
    assert main(["report", str(tmp_path / "missing"), "--out", str(tmp_path / "r")]) == 2
    assert "missing" in capsys.readouterr().err
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "summary.json").write_text('[{"victim": 1}]')
    assert main(["report", str(tmp_path / "run"), "--out", str(tmp_path / "r")]) == 2
    assert "summary.json" in capsys.readouterr().err


@needs_plugin
def test_flags_and_confidence_intervals_are_shown_when_present(tiny_run, tmp_path):
    def add(c):
        if c["attack"] == "random-shape" and c["status"] == "ok":
            c["flags"] = [{"code": "attack-raises-ap", "message": "AP rose <by> 2 points"}]
            meta = {"method": "percentile bootstrap", "statistic": "ap", "level": 0.95, "resamples": 10, "seed": 0,
                    "frames": 3, "rng": "numpy"}
            c["metrics_ci"] = {"meta": meta, "Car": {"bev": {"R40": {"moderate": [1.25, 17.5]},
                                                             "R11": {"moderate": [2.0, 3.0]}}}}
            c["attack_effect"]["drop_ci"] = {"meta": meta, "Car": {"bev": {"R40": {"moderate": [-0.5, 4.0]}}}}

    run = _copy_run(tiny_run, tmp_path / "flagged", add)
    (sec,) = rdata.sections(rdata.read_runs([run]))
    views = [SectionView(sec, rdata.table(sec))]
    page = html_page(views, "t", [str(run)], [])
    assert '<span class="flag" title="AP rose &lt;by&gt; 2 points">attack-raises-ap</span>' in page
    assert 'data-t40="[1.25, 17.50]" data-t11="[2.00, 3.00]"' in page
    assert 'data-t40="[-0.50, 4.00]" data-t11="–"' in page
    md = markdown(views, "t", [str(run)], [], "figures")
    # the message's <by> as entities: shown as written, never a tag (tests/report/test_report_trust.py renders it)
    assert "attack-raises-ap: AP rose &lt;by&gt; 2 points" in md and "[1.25, 17.50]" in md and "[-0.50, 4.00]" in md


# ---------------------------------------------------------------- the transfer matrix on hand-made cells

def _cell(victim, attack, proposals="detector", trained=None, rel="no effect", sha="a" * 64, status="ok"):
    obj = None if trained is None else {"ply_sha256": sha, "made_by": {"victim": {"name": trained}}}
    effect = None if rel == "no effect" else {"relative_drop": {"Car": {"bev": {"R40": {"moderate": rel}}}}}
    return {"victim": victim, "attack": attack, "proposals": proposals, "status": status,
            "attack_effect": effect, "provenance": {"config": {"attack": {"object": {"object": obj}}}}}


def test_transfer_matrix_on_hand_made_cells():
    cells = [
        _cell("A", "none"),  # clean: no object, no effect
        _cell("D", "objA", trained="A"),  # no clean comparison: "no clean cell"
        _cell("A", "random-shape", rel=0.9, trained=None),  # control: no row
        _cell("A", "objA", trained="A", rel=0.5),
        _cell("B", "objA", trained="A", rel=0.1),
        _cell("A", "objB", trained="B", rel=0.2, sha="b" * 64),
        _cell("C", "objB", trained="B", rel=None, sha="b" * 64),  # clean AP 0: undefined
        _cell("B", "objA", "gt", trained="A", rel=0.3),
        _cell("C", "objA", trained="A", rel=0.7, status="error"),  # not ok: its status
    ]
    m = rdata.transfer_matrix(cells, "detector")
    # every attack object (not the control) by every victim of the cells, in order of first appearance
    assert list(m.index) == [("A", "objA"), ("B", "objB")] and list(m.columns) == ["A", "D", "B", "C"]
    nan = math.nan
    expect = [[0.5, nan, 0.1, nan], [0.2, nan, nan, nan]]
    for r, row in enumerate(expect):
        for c, v in enumerate(row):
            got = m.iloc[r, c]
            assert (math.isnan(v) and math.isnan(got)) or got == v, (r, c, got, v)
    # each entry without a number says why, and the training victim's entries are white-box
    (grid, gt) = rdata.transfer_grids(cells)
    texts = [[grid.entry(row, v).text for v in grid.victims] for row in grid.rows]
    assert texts == [["50.0", "no clean cell", "10.0", "error"], ["20.0", "not run", "not run", "clean AP 0"]]
    assert [[grid.entry(row, v).white_box for v in grid.victims] for row in grid.rows] == [
        [True, False, False, False], [False, False, True, False]]
    g = rdata.transfer_matrix(cells, "gt")
    assert list(g.index) == list(m.index) and list(g.columns) == ["A", "D", "B", "C"]
    assert g.loc[("A", "objA"), "B"] == 0.3 and int(g.notna().sum().sum()) == 1
    assert [gt.entry(row, "A").text for row in gt.rows] == ["not run", "not run"]
    assert rdata.transfer_matrix([cells[0], cells[2]], "detector").empty  # clean and control: no attack object

    same_twice = [*cells, copy.deepcopy(cells[2])]
    assert rdata.transfer_matrix(same_twice, "detector").equals(m)
    with pytest.raises(RobustBenchError, match="different results"):
        rdata.transfer_matrix([*cells, _cell("A", "objA", trained="A", rel=0.6)], "detector")
    with pytest.raises(RobustBenchError, match="two different object files"):
        rdata.transfer_matrix([*cells, _cell("D", "objA", trained="A", rel=0.6, sha="c" * 64)], "detector")


# ---------------------------------------------------------------- the page in a real headless browser

@needs_plugin
def test_page_in_headless_chromium(tiny_run, tiny_report, tmp_path):
    with chromium_page(width=1280, height=1000) as (page, errors):
        page.goto((tiny_report / "leaderboard.html").as_uri())
        page.wait_for_load_state("load")
        # fits a 1280 px wide window: no sideways scroll of the page, the leaderboard within its box
        assert page.evaluate("document.documentElement.scrollWidth") <= page.evaluate("window.innerWidth") == 1280
        assert page.locator("#lb-0").evaluate("t => t.scrollWidth <= t.parentElement.clientWidth")
        table1 = page.locator("#t1-0")  # the seed paper's Table 1 beside the measured rows
        assert table1.is_visible() and page.locator("#t1-0 tr.paper").count() == 4

        images = page.locator("img")
        assert images.count() >= 3  # AP per attack, drop, one scene
        for i in range(images.count()):
            img = images.nth(i)
            img.scroll_into_view_if_needed()
            assert img.is_visible()
            box = img.bounding_box()
            assert box and box["width"] > 50 and box["height"] > 50
            assert img.evaluate("e => e.complete && e.naturalWidth > 0")

        def order():
            return page.eval_on_selector_all("#lb-0 tbody tr", "rs => rs.map(r => r.dataset.cell)")

        df = rdata.table(rdata.sections(rdata.read_runs([tiny_run]))[0])
        head = page.locator('#lb-0 th[data-key="bev_{recall}_moderate"]')
        for key, th in (("bev_R40_moderate", head), ("asr", page.locator('#lb-0 th[data-key="asr"]'))):
            th.click()
            assert order() == list(df.sort_values(key, kind="stable", na_position="last")["cell"])
            th.click()
            assert order() == list(df.sort_values(key, ascending=False, kind="stable", na_position="last")["cell"])
        # the R11 toggle switches the numbers and the sort key of the sorted column
        head.click()
        assert order() == list(df.sort_values("bev_R40_moderate", kind="stable", na_position="last")["cell"])
        page.locator('button[data-recall="R11"]').click()
        assert order() == list(df.sort_values("bev_R11_moderate", kind="stable", na_position="last")["cell"])
        first = order()[0]
        text = page.locator(f'#lb-0 tr[data-cell="{first}"] td').nth(_col(page, "bev_{recall}_moderate")).inner_text()
        row = df[df["cell"] == first].iloc[0]
        assert text == f"{row['bev_R11_moderate']:.2f}" and text != f"{row['bev_R40_moderate']:.2f}"
        page.locator('button[data-recall="R40"]').click()
        # provenance is one click away
        link = page.locator(f'#lb-0 tr[data-cell="{first}"] a.prov')
        link.click()
        assert page.locator(link.get_attribute("href")).evaluate("d => d.open") is True
        shot = tmp_path / "report.png"
        page.evaluate("window.scrollTo(0, 0); document.querySelectorAll('.wrap').forEach(w => { w.scrollLeft = 0; })")
        page.screenshot(path=str(shot), full_page=True)
    assert errors == []
    assert shot.read_bytes()[:4] == b"\x89PNG"
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copyfile(shot, ARTIFACTS / "report.png")


def _col(page, key: str) -> int:
    return page.eval_on_selector_all("#lb-0 thead th", f"hs => hs.findIndex(h => h.dataset.key === {key!r})")

"""The seed paper's Table 1 layout of a run (robustbench3d.seed_table) and its place in ``run``: hand-made
summaries with hand-computed relative drops, rows only for the cells a summary has, one section per victim."""

from __future__ import annotations

from pathlib import Path

import pytest
from seed_cells import attacked, cell

from robustbench3d.results import validate_summary
from robustbench3d.seed_table import (
    SEED_ROWS,
    SEED_TABLE_FILE,
    paper_relative_drop,
    sections,
    seed_table_markdown,
    seed_table_text,
    write_seed_table,
)

LEGEND = ("clean R40 = the 'none' cell with the same proposals; rel. drop = (clean - attacked) / clean at "
          "moderate; ASR = Cars matched clean and missed attacked (moderate, BEV IoU 0.7); seed paper = its "
          "Table 1 (one clean row, beside both proposal sources), its rel. drop against its clean row")
HEADER_MD = ("| row | proposals | BEV R40 (E M H) | BEV R11 (E M H) | clean R40 (E M H) | rel. drop M % (R40 R11) "
             "| ASR % | seed paper | paper BEV (E M H) | paper rel. drop M % |\n"
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: |")


# victim "fp": clean detector 80/64/50 (R11 81/66/52), clean gt 90/80/70 (R11 91/82/72)
FP_CLEAN_DET = cell("fp", "none", "detector", (80.0, 64.0, 50.0), (81.0, 66.0, 52.0))
FP_CLEAN_GT = cell("fp", "none", "gt", (90.0, 80.0, 70.0), (91.0, 82.0, 72.0))
# adv-texture: moderate drop 16 of 64 (R40) = 25.0 %, 11 of 66 (R11) = 16.7 %; ASR 3 of 8 = 37.5 %
FP_TEXTURE = attacked("fp", "adv-texture", "detector", (60.0, 48.0, 40.0), (62.0, 55.0, 41.0),
                      (80.0, 64.0, 50.0), (81.0, 66.0, 52.0), (20.0, 16.0, 10.0), (19.0, 11.0, 11.0),
                      (0.25, 0.25, 0.2), (19 / 81, 1 / 6, 11 / 52), 8, 3)
# adv-object: 48 of 64 = 75.0 %, 33 of 66 = 50.0 %; ASR 7 of 8 = 87.5 %
FP_OBJECT = attacked("fp", "adv-object", "detector", (40.0, 16.0, 10.0), (41.0, 33.0, 12.0),
                     (80.0, 64.0, 50.0), (81.0, 66.0, 52.0), (40.0, 48.0, 40.0), (40.0, 33.0, 40.0),
                     (0.5, 0.75, 0.8), (40 / 81, 0.5, 40 / 52), 8, 7)
# adv-shape with GT boxes: 20 of 80 = 25.0 %, 20.5 of 82 = 25.0 %; ASR 1 of 5 = 20.0 %
FP_SHAPE = attacked("fp", "adv-shape", "gt", (45.0, 60.0, 35.0), (46.0, 61.5, 36.0),
                    (90.0, 80.0, 70.0), (91.0, 82.0, 72.0), (45.0, 20.0, 35.0), (45.0, 20.5, 36.0),
                    (0.5, 0.25, 0.5), (45 / 91, 0.25, 0.5), 5, 1)
# benign sphere with GT boxes: no change, ASR 0 of 5
FP_SPHERE_GT = attacked("fp", "benign-sphere", "gt", (90.0, 80.0, 70.0), (91.0, 82.0, 72.0),
                        (90.0, 80.0, 70.0), (91.0, 82.0, 72.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
                        (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 5, 0)
# cells of the grid that are no row of the layout: adv-shape with the detector, an object file
FP_SHAPE_DET = attacked("fp", "adv-shape", "detector", (1.0, 2.0, 3.0), (1.0, 2.0, 3.0),
                        (80.0, 64.0, 50.0), (81.0, 66.0, 52.0), (79.0, 62.0, 47.0), (80.0, 64.0, 49.0),
                        (0.9875, 0.96875, 0.94), (80 / 81, 64 / 66, 49 / 52), 8, 8)
FP_OBJECT_FILE = attacked("fp", "my-object", "detector", (1.0, 2.0, 3.0), (1.0, 2.0, 3.0),
                          (80.0, 64.0, 50.0), (81.0, 66.0, 52.0), (79.0, 62.0, 47.0), (80.0, 64.0, 49.0),
                          (0.9875, 0.96875, 0.94), (80 / 81, 64 / 66, 49 / 52), 8, 8)

# victim "lc": clean AP 0 (relative drop and ASR undefined), its gt cells skipped
LC_CLEAN = cell("lc", "none", "detector", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
LC_CLEAN_GT = cell("lc", "none", "gt", status="skipped")
LC_RANDOM = attacked("lc", "random-shape", "detector", (0.0, 5.0, 0.0), (0.0, 4.0, 0.0),
                     (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, -5.0, 0.0), (0.0, -4.0, 0.0),
                     (None, None, None), (None, None, None), 0, 0)

# victim "solo": the clean cell only
SOLO_CLEAN = cell("solo", "none", "detector", (70.0, 60.0, 50.0), (71.0, 61.0, 51.0))

SUMMARY = [FP_CLEAN_DET, FP_SHAPE_DET, FP_TEXTURE, FP_OBJECT_FILE, FP_OBJECT, FP_CLEAN_GT, FP_SPHERE_GT, FP_SHAPE,
           LC_CLEAN, LC_CLEAN_GT, LC_RANDOM, SOLO_CLEAN]

FP_ROWS_MD = [
    "| clean | detector | 80.00 64.00 50.00 | 81.00 66.00 52.00 | - | - | - | clean | 85.7 83.6 76.2 | - |",
    "| clean | gt | 90.00 80.00 70.00 | 91.00 82.00 72.00 | - | - | - | clean | 85.7 83.6 76.2 | - |",
    "| benign-sphere | gt | 90.00 80.00 70.00 | 91.00 82.00 72.00 | 90.00 80.00 70.00 | 0.0 0.0 | 0.0 | - | - | - |",
    "| adv-shape | gt | 45.00 60.00 35.00 | 46.00 61.50 36.00 | 90.00 80.00 70.00 | 25.0 25.0 | 20.0 | LiDAR-only "
    "| 37.4 37.8 39.1 | 54.8 |",
    "| adv-texture | detector | 60.00 48.00 40.00 | 62.00 55.00 41.00 | 80.00 64.00 50.00 | 25.0 16.7 | 37.5 "
    "| image-only | 51.9 36.0 31.5 | 56.9 |",
    "| adv-object | detector | 40.00 16.00 10.00 | 41.00 33.00 12.00 | 80.00 64.00 50.00 | 75.0 50.0 | 87.5 "
    "| LiDAR+image | 27.5 22.7 19.2 | 72.8 |",
]
FILL_ALL = ("benign-sphere (--proposals detector,gt), random-shape (--proposals detector,gt), "
            "adv-shape (--proposals gt), adv-texture (--proposals detector), adv-object (--proposals detector)")


def test_fake_summary_is_schema_valid():
    validate_summary(SUMMARY)


def test_paper_relative_drops_by_hand():
    """(83.6 - 37.8) / 83.6, (83.6 - 36.0) / 83.6, (83.6 - 22.7) / 83.6 from the paper's Table 1."""
    papers = {r.attack: r.paper for r in SEED_ROWS if r.paper is not None}
    assert paper_relative_drop(papers["adv-shape"]) == pytest.approx(45.8 / 83.6, rel=1e-12)
    assert paper_relative_drop(papers["adv-texture"]) == pytest.approx(47.6 / 83.6, rel=1e-12)
    assert paper_relative_drop(papers["adv-object"]) == pytest.approx(60.9 / 83.6, rel=1e-12)
    assert papers["none"].bev == (85.7, 83.6, 76.2)
    assert [(r.attack, r.proposals) for r in SEED_ROWS if r.paper not in (None, papers["none"])] == [
        ("adv-shape", "gt"), ("adv-texture", "detector"), ("adv-object", "detector")]


def test_markdown_layout_exactly():
    expected = "\n".join([
        "# Seed paper Table 1 layout", "",
        f"Car BEV AP in % at IoU 0.70, easy / moderate / hard; {LEGEND}.", "",
        "## fp", "", "12 frames.", "", HEADER_MD, *FP_ROWS_MD, "",
        "- not in this run: benign-sphere / detector, random-shape / detector, random-shape / gt", "",
        "## lc", "", "12 frames.", "", HEADER_MD,
        "| clean | detector | 0.00 0.00 0.00 | 0.00 0.00 0.00 | - | - | - | clean | 85.7 83.6 76.2 | - |",
        "| random-shape | detector | 0.00 5.00 0.00 | 0.00 4.00 0.00 | 0.00 0.00 0.00 | - - | - | - | - | - |", "",
        "- no AP: none / gt: skipped: victim supports proposals detector only",
        "- not in this run: benign-sphere / detector, benign-sphere / gt, random-shape / gt, adv-shape / gt, "
        "adv-texture / detector, adv-object / detector", "",
        "## solo", "", "12 frames.", "",
        "| row | proposals | BEV R40 (E M H) | BEV R11 (E M H) | clean R40 (E M H) | rel. drop M % (R40 R11) "
        "| ASR % | seed paper | paper BEV (E M H) | paper rel. drop M % |\n"
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: |",
        "| clean | detector | 70.00 60.00 50.00 | 71.00 61.00 51.00 | - | - | - | clean | 85.7 83.6 76.2 | - |", "",
        f"- no attacked cell of the layout; these attacks fill it: {FILL_ALL}", "",
    ])
    assert seed_table_markdown(SUMMARY) == expected


def test_text_layout_exactly():
    """The printed section of one victim: the run table's padding (6.2f AP, two spaces between columns)."""
    summary = [FP_CLEAN_GT, FP_SHAPE]
    expected = "\n".join([
        "Seed paper Table 1 layout: Car BEV AP in % at IoU 0.70, easy / moderate / hard",
        LEGEND,
        "victim fp, 12 frames",
        "row        proposals       BEV R40 (E M H)       BEV R11 (E M H)     clean R40 (E M H)  "
        "rel. drop M % (R40 R11)  ASR %  seed paper  paper BEV (E M H)  paper rel. drop M %",
        "---------  ---------  --------------------  --------------------  --------------------  "
        "-----------------------  -----  ----------  -----------------  -------------------",
        "clean      gt          90.00  80.00  70.00   91.00  82.00  72.00                     -  "
        "                      -      -  clean          85.7 83.6 76.2                    -",
        "adv-shape  gt          45.00  60.00  35.00   46.00  61.50  36.00   90.00  80.00  70.00  "
        "              25.0 25.0   20.0  LiDAR-only     37.4 37.8 39.1                 54.8",
        "not in this run: benign-sphere / detector, benign-sphere / gt, random-shape / detector, random-shape / gt, "
        "adv-texture / detector, adv-object / detector",
    ])
    assert seed_table_text(summary) == expected


def test_text_and_markdown_carry_the_same_rows():
    text = seed_table_text(SUMMARY)
    for row in FP_ROWS_MD:
        cells = [c.strip() for c in row.strip("|").split("|")]
        line = next(line for line in text.splitlines() if line.split()[:2] == cells[:2])
        assert " ".join(line.split()) == " ".join(" ".join(cells).split())


def test_rows_only_for_cells_the_summary_has():
    rows = {s.victim: [(r[0], r[1]) for r in s.rows] for s in sections(SUMMARY)}
    # adv-shape / detector and the object file are in the grid but are no rows of the layout
    assert rows == {
        "fp": [("clean", "detector"), ("clean", "gt"), ("benign-sphere", "gt"), ("adv-shape", "gt"),
               ("adv-texture", "detector"), ("adv-object", "detector")],
        "lc": [("clean", "detector"), ("random-shape", "detector")],
        "solo": [("clean", "detector")],
    }
    # removing a cell removes its row and names it as missing
    without = [c for c in SUMMARY if c is not FP_OBJECT]
    fp = sections(without)[0]
    assert ("adv-object", "detector") not in [(r[0], r[1]) for r in fp.rows]
    assert "adv-object / detector" in seed_table_text(without)


def test_sections_per_victim_in_summary_order():
    reordered = [SOLO_CLEAN, *SUMMARY[:-1]]
    assert [s.victim for s in sections(reordered)] == ["solo", "fp", "lc"]
    text = seed_table_text(reordered)
    assert [line for line in text.splitlines() if line.startswith("victim ")] == [
        "victim solo, 12 frames", "victim fp, 12 frames", "victim lc, 12 frames"]


@pytest.mark.parametrize("summary", [
    [SOLO_CLEAN],
    [FP_CLEAN_DET, FP_CLEAN_GT, LC_CLEAN, LC_CLEAN_GT],
    [FP_CLEAN_DET, FP_OBJECT_FILE, FP_SHAPE_DET],  # attacked cells, none of them a row of the layout
    [],
])
def test_no_attacked_cell_no_table_only_the_attacks_that_fill_it(summary):
    line = f"no attacked cell of it in this run; these attacks fill it: {FILL_ALL}"
    assert seed_table_text(summary) == f"Seed paper Table 1 layout: {line}"
    assert seed_table_markdown(summary) == f"# Seed paper Table 1 layout\n\n{line[0].upper()}{line[1:]}.\n"


def test_write_seed_table_is_the_markdown(tmp_path):
    path = tmp_path / SEED_TABLE_FILE
    text = write_seed_table(path, SUMMARY)
    assert path.read_text(encoding="utf-8") == text == seed_table_markdown(SUMMARY)
    assert [p.name for p in tmp_path.iterdir()] == [SEED_TABLE_FILE]  # no temporary file left


@pytest.fixture
def fake_run(monkeypatch):
    """``robustbench3d run`` with :func:`run_benchmark` replaced: writes summary.json and returns a report of
    :data:`SUMMARY` (or raises ``fail``)."""
    import robustbench3d.runner as runner
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.results import write_validated
    from robustbench3d.runner.config import CellKey

    state: dict = {"fail": None}

    def run_benchmark(config, executor=None):
        if state["fail"] is not None:
            if state["fail"] == "after-lock":  # the real runner removes the derived summary first
                (Path(config.out) / "summary.json").unlink(missing_ok=True)
            raise RobustBenchError("boom")
        out = Path(config.out)
        out.mkdir(parents=True, exist_ok=True)
        write_validated(out / "summary.json", SUMMARY)
        outcomes = [runner.CellOutcome(CellKey(c["victim"], c["attack"], c["proposals"]), c, reused=False)
                    for c in SUMMARY]
        return runner.RunReport(out=out, dataset=SUMMARY[0]["dataset"], outcomes=outcomes)

    monkeypatch.setattr(runner, "run_benchmark", run_benchmark)
    return state


def run_main(out: Path) -> int:
    from robustbench3d.cli import main

    return main(["run", "--victims", "fp,lc,solo", "--attacks", "none,adv-shape", "--proposals", "detector,gt",
                 "--out", str(out), "--no-progress"])


def test_run_prints_the_layout_after_the_grid_and_writes_seed_table_md(fake_run, tmp_path, capsys):
    out = tmp_path / "run"
    assert run_main(out) == 0
    printed = capsys.readouterr().out
    grid_at = printed.index("BEV R40 (E M H)")
    seed_at = printed.index("Seed paper Table 1 layout: ")
    assert grid_at < printed.index(f"results: {out / 'summary.json'}") < seed_at
    assert seed_table_text(SUMMARY) in printed
    assert printed.rstrip("\n").endswith(f"seed table: {out / SEED_TABLE_FILE}")

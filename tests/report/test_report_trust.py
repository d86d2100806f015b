"""``robustbench3d report`` trusted on real runs: scene figures of a ``--max-frames`` run whose later frames
do not exist (the README's main job), a label change of an evaluated frame still noticed, every summary
string inert in ``leaderboard.md`` and ``leaderboard.html``, the written-once rule of ``--out`` and the
range of ``--scenes``, all refused up front in one line."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import shutil
from html.parser import HTMLParser
from pathlib import Path

import pytest

from robustbench3d.cli import main

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("rb3d_lidar_cluster") is None,
    reason="example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim",
)

SPLIT_FRAMES, EVALUATED = 6, 3
FRAME_DIRS = ("label_2", "velodyne", "image_2", "calib")


@pytest.fixture(scope="module")
def partial(tmp_path_factory, shared_split) -> tuple[Path, Path, list[str]]:
    """A 3-frame ``--max-frames`` run of a 6-frame split whose last 3 frames' files were then deleted (as in
    the embedded dataset's cache, generated only for the frames a run evaluates): (dataset, run, split ids).
    ``dataset.parent / "whole"`` is a copy of the dataset with every frame."""
    root = tmp_path_factory.mktemp("partial")
    ds = root / "ds"
    shutil.copytree(shared_split(SPLIT_FRAMES, seed=5, val_fraction=1.0), ds)  # its own copy: frames go below
    run = root / "run"
    assert main(["run", "--victims", "lidar-cluster", "--attacks", "none,random-shape,benign-sphere",
                 "--proposals", "detector", "--data", str(ds), "--out", str(run), "--max-frames", str(EVALUATED),
                 "--no-progress", "--jobs", "1"]) == 0
    ids = (ds / "ImageSets" / "val.txt").read_text().split()
    assert len(ids) == SPLIT_FRAMES
    shutil.copytree(ds, root / "whole")  # the whole split, every frame present
    for fid in ids[EVALUATED:]:
        for sub in FRAME_DIRS:
            for f in (ds / "training" / sub).glob(f"{fid}.*"):
                f.unlink()
    return ds, run, ids


def _report(run: Path | list[Path], out: Path, *extra: str) -> int:
    return main(["report", *map(str, run if isinstance(run, list) else [run]), "--out", str(out), *extra])


def _scene_files(out: Path) -> list[Path]:
    return sorted((out / "figures").glob("*scene*.png"))


def _rooted(run: Path, ds: Path, dst: Path) -> Path:
    """A copy of the run whose summary says it evaluated dataset ``ds``."""
    run2 = Path(shutil.copytree(run, dst))
    cells = json.loads((run2 / "summary.json").read_text())
    for c in cells:
        c["dataset"]["root"] = c["provenance"]["config"]["dataset"]["root"] = str(ds)
    (run2 / "summary.json").write_text(json.dumps(cells))
    return run2


# ------------------------------------------------------------------ scene figures of a --max-frames run

@pytest.mark.parametrize("later_frames", ["deleted", "present"])
def test_scene_figures_of_a_max_frames_run(partial, tmp_path, capsys, later_frames):
    ds, run, ids = partial
    if later_frames == "present":  # the dataset complete: the split's other labels are not the run's frames
        ds = ds.parent / "whole"
        run = _rooted(run, ds, tmp_path / "run")
    cells = json.loads((run / "summary.json").read_text())
    assert {(c["dataset"]["frames"], c["dataset"]["split_frames"]) for c in cells} == {(EVALUATED, SPLIT_FRAMES)}
    assert (ds / "training" / "label_2" / f"{ids[-1]}.txt").exists() == (later_frames == "present")
    out = tmp_path / "rep"
    assert _report(run, out, "--scenes", "2") == 0
    scenes = _scene_files(out)
    assert len(scenes) == 2  # random-shape and benign-sphere, each on one of the evaluated frames
    assert all(p.read_bytes()[:4] == b"\x89PNG" and p.stem.rsplit("_", 1)[1] in ids[:EVALUATED] for p in scenes)
    texts = [(out / "leaderboard.md").read_text(encoding="utf-8"), (out / "leaderboard.html").read_text("utf-8"),
             capsys.readouterr().out]
    for text in texts:
        assert "changed since the run" not in text and "cannot be read" not in text
        assert "no scene figure" not in text


def test_a_label_change_of_an_evaluated_frame_is_still_noticed(partial, tmp_path):
    ds, run, ids = partial
    ds2 = shutil.copytree(ds, tmp_path / "ds")
    run2 = _rooted(run, ds2, tmp_path / "run")
    assert _report(run2, tmp_path / "same", "--scenes", "1") == 0 and len(_scene_files(tmp_path / "same")) == 1
    label = ds2 / "training" / "label_2" / f"{ids[0]}.txt"
    original = label.read_bytes()
    label.write_bytes(original + b"DontCare -1 -1 -10 0.00 0.00 10.00 10.00 -1 -1 -1 -1000 -1000 -1000 -10\n")
    assert _report(run2, tmp_path / "changed", "--scenes", "1") == 0
    md = (tmp_path / "changed" / "leaderboard.md").read_text(encoding="utf-8")
    assert "has changed since the run" in md and _scene_files(tmp_path / "changed") == []
    label.write_bytes(original)
    (ds2 / "training" / "label_2" / f"{ids[EVALUATED - 1]}.txt").unlink()  # an evaluated frame's labels gone
    assert _report(run2, tmp_path / "missing", "--scenes", "1") == 0
    md = (tmp_path / "missing" / "leaderboard.md").read_text(encoding="utf-8")
    assert "cannot be read as the run read it" in md and f"{ids[EVALUATED - 1]}.txt" in md
    assert _scene_files(tmp_path / "missing") == []


# ------------------------------------------------------------------ hostile strings in a summary

SCRIPT = "<script>alert(1)</script>"
IMG = "<img src=x onerror=alert(2)>"
LINK = "[x](javascript:alert(3))"
IMAGE = "![i](javascript:alert(4))"
HOSTILE = f"{SCRIPT} {IMG} {LINK} {IMAGE} a|b `c` *d* _e_ &amp; \n# heading"


class Tags(HTMLParser):
    """Every start tag with its attributes, and the text, of an HTML document."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.tags: list[tuple[str, dict[str, str]]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, {k: v or "" for k, v in attrs}))

    def handle_data(self, data):
        self.text.append(data)


def _tags(html_text: str) -> Tags:
    p = Tags()
    p.feed(html_text)
    return p


def _assert_inert(doc: Tags, img_prefix: str) -> None:
    for tag, attrs in doc.tags:
        assert not any(k.startswith("on") for k in attrs), (tag, attrs)
        assert not any(v.strip().lower().startswith("javascript:") for v in attrs.values()), (tag, attrs)
        if tag == "img":
            assert attrs["src"].startswith(img_prefix), attrs


def _inert_report(out: Path, *, raw_markdown: bool = True) -> tuple[str, Tags]:
    """The report in ``out`` checked as every hostile-strings test checks it: none of the hostile strings raw in
    the page (nor, with ``raw_markdown``, in the markdown), the page's own sorting script its only one, its tags
    inert; (the markdown, the page's tags)."""
    md = (out / "leaderboard.md").read_text(encoding="utf-8")
    page = (out / "leaderboard.html").read_text(encoding="utf-8")
    if raw_markdown:
        for raw in (SCRIPT, IMG, "<img", "<script>alert", LINK, IMAGE, "\n# heading"):
            assert raw not in md, raw
    for raw in (SCRIPT, IMG, "<img src=x", "<script>alert"):
        assert raw not in page, raw
    doc = _tags(page)
    assert [t for t, _ in doc.tags].count("script") == 1
    _assert_inert(doc, "data:image/png;base64,")
    return md, doc


def test_summary_strings_are_inert_in_markdown_and_html(partial, tmp_path):
    _, run, _ = partial
    hostile = shutil.copytree(run, tmp_path / "hostile")
    cells = json.loads((hostile / "summary.json").read_text())
    for c in cells:
        c["dataset"]["root"] = f"/nowhere/{IMG}"
        c["dataset"]["split"] = f"{SCRIPT}{LINK}"
        c["flags"] = [{"code": "hostile", "message": HOSTILE}]
    (hostile / "summary.json").write_text(json.dumps(cells))
    out = tmp_path / "rep"
    assert _report(hostile, out, "--title", f"t {SCRIPT} {LINK}") == 0
    md, doc = _inert_report(out)
    # shown as given: the flag's tooltip, and the cell's JSON
    assert ("span", {"class": "flag", "title": HOSTILE}) in doc.tags
    assert json.dumps(HOSTILE, ensure_ascii=False) in "".join(doc.text)

    # rendered by an independent CommonMark renderer (with tables): no markup from the summary, and the text
    # reads as given; every table row has the header's number of cells (a | in a string splits none)
    rendered, text = _rendered(md)
    assert f"{SCRIPT}{LINK}" in text and IMG in text
    assert "a|b `c` *d* _e_ &amp;  # heading" in text  # on one line: the line break a space
    tables = [_head_rows(t) for t in rendered.split("<table>")[1:]]
    assert len(tables) == 2  # the Table 1 block and the leaderboard
    for head, rows in tables:
        assert all(r.count("<td>") == head.count("<th>") for r in rows)
    head, rows = tables[1]
    assert len(rows) == len(cells) and head.count("<th>") > 10


def _head_rows(table: str) -> tuple[str, list[str]]:
    """A rendered table's head and its body rows."""
    head, body = table.split("</table>")[0].split("<tbody>")
    return head, body.split("</tbody>")[0].split("<tr>")[1:]


def test_table1_and_cell_notes_strings_are_inert(partial, tmp_path):
    """A skipped cell's reason (Table 1's no-AP line, the notes) and run directories with markup in their names
    (the notes on the cells merged): shown as given, never markup, in the page and in the markdown."""
    _, run, _ = partial
    first = shutil.copytree(run, tmp_path / f"r{IMG}")
    cells = json.loads((first / "summary.json").read_text())
    for c in cells:
        if c["attack"] == "none":
            c.update(status="skipped", reason=HOSTILE, metrics=None)
            for key in ("metrics_ci", "attack_effect"):
                c.pop(key, None)
    (first / "summary.json").write_text(json.dumps(cells))
    second = shutil.copytree(first, tmp_path / f"s{LINK}")  # the same cells again: merged, each named
    out = tmp_path / "rep"
    assert _report([first, second], out, "--scenes", "0") == 0
    md, doc = _inert_report(out, raw_markdown=False)
    text = "".join(doc.text)
    assert f"no AP: skipped: {HOSTILE}" in text  # Table 1's line for the clean cell
    i = next(k for k, c in enumerate(cells) if c["attack"] == "none")
    assert f"({second / 'summary.json'}[{i}]) is left out: it is the same cell as {first / 'summary.json'}[{i}]" in text
    _, md_text = _rendered(md)
    assert f"({second / 'summary.json'}[{i}]) is left out" in md_text
    assert "# heading" in md_text and HOSTILE.splitlines()[0] in md_text


def test_the_page_template_escapes_every_value():
    """The page's Jinja2 template: autoescape on, nothing marked safe, so any value it shows is escaped."""
    from robustbench3d.report.page import TEMPLATE, environment

    env = environment()
    assert env.autoescape is True
    source = env.loader.get_source(env, TEMPLATE)[0]
    squeezed = source.replace(" ", "")
    assert "|safe" not in squeezed and "{%autoescape" not in squeezed and "Markup" not in source
    html_text = env.get_template(TEMPLATE).render(title=SCRIPT, runs=IMG, notes=[HOSTILE], sections=[], trades=[],
                                                  groups=[("3d", LINK)])
    for raw in (SCRIPT, IMG, "<img src=x"):
        assert raw not in html_text, raw
    doc = _tags(html_text)
    assert [t for t, _ in doc.tags].count("script") == 1 and SCRIPT in "".join(doc.text)
    assert ("p", {"class": "why"}) in doc.tags and HOSTILE in "".join(doc.text)


def _rendered(md: str) -> tuple[str, str]:
    """``md`` rendered by markdown-it (CommonMark with tables; skip without it), checked inert: no script,
    no link, images only of the report's figures, no event handler; (HTML, its text)."""
    markdown_it = pytest.importorskip("markdown_it")
    rendered = markdown_it.MarkdownIt("commonmark").enable("table").render(md)
    doc = _tags(rendered)
    names = [t for t, _ in doc.tags]
    assert "script" not in names and "a" not in names and names.count("h1") == 1
    _assert_inert(doc, "figures/")
    return rendered, "".join(doc.text)


@pytest.mark.filterwarnings("ignore:No artists with labels:UserWarning")  # a one-sweep figure
def test_tradeoff_strings_are_inert_in_markdown_and_html(tmp_path, shared_split):
    ds = shared_split(2, seed=5, val_fraction=1.0)
    trade = tmp_path / "trade"
    assert main(["tradeoff", "--out", str(trade), "--data", str(ds), "--frames", "2", "--attack", "random-shape",
                 "--victim", "lidar-cluster", "--sweeps", "frames", "--resamples", "20", "--no-progress"]) == 0
    doc = json.loads((trade / "tradeoff.json").read_text(encoding="utf-8"))
    doc["config"]["victim"] = f"v {IMG}"
    doc["machine"].update(cpu=f"{SCRIPT} {LINK}", cpu_count=IMAGE)
    doc["sweeps"] = {k: HOSTILE for k in doc["sweeps"]}
    for point in doc["points"]:
        point["value"] = HOSTILE
    (trade / "tradeoff.json").write_text(json.dumps(doc), encoding="utf-8")
    out = tmp_path / "rep"
    assert main(["report", "--tradeoff", str(trade), "--out", str(out)]) == 0
    md, tags = _inert_report(out)
    assert f"{SCRIPT} {LINK}" in "".join(tags.text) and f"({IMAGE} cores)" in "".join(tags.text)
    _, text = _rendered(md)
    assert f"v {IMG}" in text and f"{SCRIPT} {LINK}" in text and "a|b `c` *d* _e_ &amp;  # heading" in text


# ------------------------------------------------------------------ --out: written once, checked up front

def _tree(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(root.rglob("*"))}


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("robustbench3d: error: ") and "\n" not in err, err
    return err


def test_report_inside_the_run_directory_is_replaced_by_the_next_one(partial, tmp_path, capsys):
    _, run, _ = partial
    run = shutil.copytree(run, tmp_path / "run")
    other = shutil.copytree(run, tmp_path / "other")  # another dataset: the report's section 2
    cells = json.loads((other / "summary.json").read_text())
    for c in cells:
        c["dataset"]["sha256"] = c["provenance"]["config"]["dataset"]["sha256"] = "0" * 64
    (other / "summary.json").write_text(json.dumps(cells))
    before = _tree(run)
    report = run / "report"  # the README's flow
    assert _report([run, other], report, "--scenes", "0") == 0
    second = sorted((report / "figures").glob("s2_*.png"))
    assert len(second) >= 2 and (report / "leaderboard.md").is_file()
    (report / "my notes.txt").write_text("mine")
    capsys.readouterr()
    assert _report(run, report, "--scenes", "0") == 0  # section 2 no longer written
    said = [ln for ln in capsys.readouterr().out.splitlines() if "replacing the report written earlier" in ln]
    assert len(said) == 1 and f"{len(second)} no longer written, removed" in said[0]
    assert "1 other entry kept" in said[0] and (report / "my notes.txt").read_text() == "mine"
    assert not any(p.exists() for p in second) and "Section 2" not in (report / "leaderboard.md").read_text("utf-8")
    assert {k: v for k, v in _tree(run).items() if not k.startswith("report")} == before  # the run is untouched
    # a file no earlier report wrote, where the next one would write: refused, then replaced under --force
    second[0].write_bytes(b"not the report's")
    assert _report([run, other], report, "--scenes", "0") == 2
    assert "--force" in _one_line_error(capsys) and second[0].read_bytes() == b"not the report's"
    assert not second[1].exists()  # nothing was written
    assert _report([run, other], report, "--scenes", "0", "--force") == 0
    assert f"replacing {second[0]} (--force)" in capsys.readouterr().out
    assert second[0].read_bytes()[:4] == b"\x89PNG"


def test_a_non_empty_directory_that_holds_no_report_is_refused_unless_force(partial, tmp_path, capsys):
    _, run, _ = partial
    before = _tree(run)
    assert _report(run, run, "--scenes", "0") == 2  # the run directory itself
    err = _one_line_error(capsys)
    assert "not empty" in err and "--force" in err and _tree(run) == before
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "leaderboard.md").write_text("my own leaderboard")
    (mine / "other.txt").write_text("keep me")
    assert _report(run, mine, "--scenes", "0") == 2
    _one_line_error(capsys)
    assert sorted(p.name for p in mine.iterdir()) == ["leaderboard.md", "other.txt"]
    assert (mine / "leaderboard.md").read_text() == "my own leaderboard"
    # a manifest that does not list only the report's own files is not an earlier report's
    (mine / "report_manifest.json").write_text(json.dumps({"written_by": "robustbench3d report",
                                                           "files": ["other.txt"]}))
    assert _report(run, mine, "--scenes", "0") == 2
    assert "other.txt" in _one_line_error(capsys) and (mine / "other.txt").read_text() == "keep me"
    assert _report(run, mine, "--scenes", "0", "--force") == 0
    out = capsys.readouterr().out
    assert f"replacing {mine / 'leaderboard.md'} (--force)" in out
    assert (mine / "leaderboard.md").read_text(encoding="utf-8").startswith("# robustbench3d leaderboard")
    assert (mine / "other.txt").read_text() == "keep me"


def test_a_broken_symlink_as_out_is_refused_in_one_line(partial, tmp_path, capsys):
    _, run, _ = partial
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "gone")
    assert _report(run, link, "--scenes", "0") == 2
    assert "broken symbolic link" in _one_line_error(capsys)
    assert link.is_symlink() and not (tmp_path / "gone").exists()


@pytest.mark.parametrize("scenes", ["-1", "21"])
def test_scenes_outside_its_range_is_refused_before_anything_else(tmp_path, capsys, scenes):
    out = tmp_path / "rep"
    assert main(["report", str(tmp_path / "no-run"), "--out", str(out), "--scenes", scenes]) == 2
    err = _one_line_error(capsys)
    assert "--scenes must be in 0..20" in err and scenes in err and not out.exists()


# ------------------------------------------------------------------ the template ships with the package

def test_templates_are_package_data_and_jinja2_tabulate_dependencies():
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    from fnmatch import fnmatch

    repo = Path(__file__).resolve().parents[2]
    data = tomllib.loads((repo / "pyproject.toml").read_text(encoding="utf-8"))
    globs = data["tool"]["setuptools"]["package-data"]["robustbench3d.report"]
    templates = repo / "robustbench3d" / "report" / "templates"
    files = [p.relative_to(templates.parent).as_posix() for p in templates.iterdir() if p.is_file()]
    assert "templates/leaderboard.html.j2" in files
    assert all(any(fnmatch(f, g) for g in globs) for f in files), (files, globs)
    names = {d.split(">")[0].split("<")[0].split("=")[0].strip().lower() for d in data["project"]["dependencies"]}
    assert {"jinja2", "tabulate"} <= names

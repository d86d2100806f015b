"""Registry bookkeeping a plugin author or user relies on (issue #11): invalid entry-point names
are rejected with the distribution named, a plugin that fails to import says so, the example
plugin's install lines work from the directory they name, ``victims remove`` undoes
``victims add-onnx``, ONNX registrations are listed as such, non-ASCII folder names become
readable victim names, a UTF-8 byte-order mark in a user file is reported, and the user registry
file is read on first use, not at import."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from plugin_dists import write_dist

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import sha256_file
from robustbench3d.kitti.calib import read_calibration
from robustbench3d.registry import sanitise_name
from robustbench3d.testing import link_frames
from robustbench3d.victims import VICTIMS
from robustbench3d.victims.onnx.registration import user_registry_file
from robustbench3d.victims.shipped import weights_dir

REPO = Path(__file__).resolve().parents[2]
BOM = "file starts with a UTF-8 byte-order mark; save it without BOM"
LABEL = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n"


def cli(*args: str, cache: Path, site: Path | None = None) -> subprocess.CompletedProcess:
    """``python -m robustbench3d ARGS`` in a fresh process (plugins on ``site`` if given)."""
    env = {"PATH": "", "ROBUSTBENCH3D_CACHE": str(cache), "OMP_NUM_THREADS": "1"}
    if site is None:
        env["ROBUSTBENCH3D_NO_PLUGINS"] = "1"
    else:
        env["PYTHONPATH"] = str(site)
    return subprocess.run([sys.executable, "-m", "robustbench3d", *args], capture_output=True, text=True, env=env)


@pytest.fixture
def two_frames(kitti_samples, tmp_path) -> Path:
    """A KITTI-layout dataset of two real frames (symlinks) with a val split."""
    return link_frames(kitti_samples, tmp_path / "data", ["000002", "000003"])


def onnx_copy(parent: Path, folder: str) -> Path:
    """A copy of the shipped ONNX victim directory under a folder name of our choice."""
    src = weights_dir() / "fpointnet-v1-lite-onnx"
    if not (src / "manifest.json").is_file():
        pytest.skip("the shipped ONNX victim is not present")
    return Path(shutil.copytree(src, parent / folder))


# ---- 1. invalid entry-point names ------------------------------------------------------------
def test_invalid_entry_point_name_is_rejected_naming_the_distribution(tmp_path, cache):
    site = tmp_path / "site"
    write_dist(site, "rb3d-shouty", "0.2.0", {"Bad_Victim": "rb3d_shouty_mod:SPEC"})
    want = ("plugin 'rb3d-shouty' 0.2.0: entry point 'Bad_Victim' (= rb3d_shouty_mod:SPEC) of group "
            "robustbench3d.victims is not a valid victim name")
    listed = cli("victims", "list", cache=cache, site=site)
    assert listed.returncode == 0, listed.stderr
    assert f"robustbench3d: warning: {want}" in listed.stderr and "(e.g. 'bad_victim')" in listed.stderr
    assert "Bad_Victim" not in listed.stdout and "fpointnet-v1-lite " in listed.stdout
    as_json = cli("victims", "list", "--json", cache=cache, site=site)
    assert want in as_json.stderr and "Bad_Victim" not in {r["name"] for r in json.loads(as_json.stdout)}
    for asked in ("Bad_Victim", "bad_victim"):  # the name as declared, and as the user would type it
        proc = cli("run", "--victims", asked, "--out", str(tmp_path / "out"), "--data", str(tmp_path / "none"),
                   cache=cache, site=site)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr
        assert f"robustbench3d: error: {want}" in proc.stderr
    # without the plugin on the path there is nothing to warn about
    assert "warning" not in cli("victims", "list", cache=cache, site=tmp_path).stderr


# ---- 2. the example plugin's install lines ---------------------------------------------------
def _pip_paths(line: str, cwd: Path) -> tuple[Path, Path]:
    args = shlex.split(line)
    assert args[:2] == ["pip", "install"], line
    return cwd / args[args.index("-c") + 1], cwd / args[args.index("-e") + 1]


def test_plugin_install_lines_work_from_the_directory_they_name():
    plugin = REPO / "examples" / "lidar_cluster_victim"
    text = (plugin / "README.md").read_text(encoding="utf-8")
    # every pip line follows the sentence that says where to run it
    where = {"from the repository root:": REPO, "from this directory (`examples/lidar_cluster_victim`):": plugin}
    blocks = re.findall(r"([^\n]*)\n\n```\n(pip install [^\n]*)\n```", text)
    assert len(blocks) == 2, blocks
    for intro, line in blocks:
        cwd = next(d for phrase, d in where.items() if intro.rstrip().endswith(phrase))
        constraints, project = _pip_paths(line, cwd)
        assert constraints.resolve() == REPO / "constraints.txt" and constraints.is_file()
        assert project.resolve() == plugin and 'name = "rb3d-lidar-cluster"' in (project / "pyproject.toml").read_text()
    # the main README's lines run from the repository root (it says so) and install the same plugin
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    main_lines = [m.strip() for m in re.findall(r"pip install -c constraints\.txt[^\n&]*", readme)]
    assert main_lines
    for line in main_lines:
        constraints, project = _pip_paths(line.replace(' -e ".[dev,onnx]"', ""), REPO)
        assert constraints.is_file() and project.resolve() == plugin


# ---- 3. a plugin that fails to import --------------------------------------------------------
def test_plugin_import_error_names_the_plugin_not_victim_args(tmp_path, cache, two_frames):
    site = tmp_path / "site"
    write_dist(site, "rb3d-broken", "1.4.0", {"broken-victim": "rb3d_broken_mod:SPEC"})
    (site / "rb3d_broken_mod.py").write_text(textwrap.dedent("""
        raise ImportError("libfoo.so.1: cannot open shared object file")
    """))
    want = ("victim plugin rb3d-broken 1.4.0 failed to import: its entry point 'broken-victim = rb3d_broken_mod:SPEC' "
            "(robustbench3d.victims) raised ImportError: libfoo.so.1: cannot open shared object file; reinstall or "
            "fix the plugin package 'rb3d-broken', or uninstall it")
    listed = cli("victims", "list", "--json", "broken-*", cache=cache, site=site)
    assert listed.returncode == 1
    [row] = json.loads(listed.stdout)
    assert row["origin"] == "plugin rb3d-broken 1.4.0" and row["error"].startswith(want)
    proc = cli("run", "--victims", "broken-victim", "--proposals", "gt", "--data", str(two_frames),
               "--out", str(tmp_path / "out"), "--no-progress", cache=cache, site=site)
    assert proc.returncode == 1
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    [cell] = summary if isinstance(summary, list) else summary["cells"]
    assert cell["status"] == "error" and want in cell["reason"]
    assert "--victim-arg" not in cell["reason"]


# ---- 4, 5, 6. add-onnx from a non-ASCII folder, listed as ONNX, then removed ------------------
def test_add_onnx_non_ascii_folder_listing_and_remove(tmp_path, cache, capsys):
    directory = onnx_copy(tmp_path, "nüscénes-dét")
    assert main(["victims", "add-onnx", str(directory)]) == 0
    assert "registered ONNX victim 'nuscenes-det'" in capsys.readouterr().out
    path = user_registry_file()
    assert json.loads(path.read_text())["victims"] == {"nuscenes-det": str(directory.resolve())}
    # listed as an ONNX registration, in this process and in a fresh one
    assert main(["victims", "list", "--json", "nuscenes-*"]) == 0
    [row] = json.loads(capsys.readouterr().out)
    assert row["origin"] == "onnx user registry" and row["capabilities"]["backend"] == "onnx"
    assert row["weights_sha256"] == sha256_file(directory / "manifest.json")
    fresh = cli("victims", "list", "--json", cache=cache)
    origins = {r["name"]: r["origin"] for r in json.loads(fresh.stdout)}
    assert origins["nuscenes-det"] == "onnx user registry" and origins["fpointnet-v1-lite-onnx"] == "onnx shipped"
    assert origins["fpointnet-v1-lite"] == "in-tree"
    table = cli("victims", "list", "nuscenes-det", cache=cache).stdout.splitlines()
    assert "onnx user registry" in table[1]

    # remove: in-tree and shipped victims are refused, unknown names exit 2, the entry goes
    assert main(["victims", "remove", "fpointnet-v1-lite"]) == 2
    assert "(in-tree) was not added with `victims add-onnx`" in capsys.readouterr().err
    assert main(["victims", "remove", "fpointnet-v1-lite-onnx"]) == 2
    assert "(onnx shipped) was not added with `victims add-onnx`" in capsys.readouterr().err
    assert main(["victims", "remove", "nuscenes-dt"]) == 2
    assert "unknown victim 'nuscenes-dt'; did you mean 'nuscenes-det'" in capsys.readouterr().err
    assert main(["victims", "remove", "nuscenes-det"]) == 0
    assert f"removed ONNX victim 'nuscenes-det' (was {directory.resolve()}) from {path}" in capsys.readouterr().out
    assert json.loads(path.read_text()) == {"format": "robustbench3d.onnx_victims/1", "victims": {}}
    assert directory.is_dir() and "nuscenes-det" not in VICTIMS
    assert "nuscenes-det" not in {r["name"] for r in json.loads(cli("victims", "list", "--json", cache=cache).stdout)}
    assert main(["victims", "remove", "nuscenes-det"]) == 2  # gone: now unknown
    assert "unknown victim 'nuscenes-det'" in capsys.readouterr().err


def test_unreadable_folder_names_require_a_name(tmp_path, cache, capsys):
    # hand-folded references
    assert sanitise_name("nüscénes-dét") == "nuscenes-det"
    assert sanitise_name("Ålesund Übung") == "alesund-ubung"
    assert sanitise_name("ﬁne_Run.v2") == "fine_run.v2"  # compatibility ligature
    assert sanitise_name("日本語") == "" and sanitise_name("kitti-日本") == "" and sanitise_name("  //") == ""
    directory = onnx_copy(tmp_path, "日本語")
    assert main(["victims", "add-onnx", str(directory)]) == 2
    err = capsys.readouterr().err
    assert f"{directory}: no victim name can be derived from the folder name '日本語'" in err
    assert "give one with --name NAME" in err and not user_registry_file().exists()
    assert main(["victims", "add-onnx", str(directory), "--name", "kitti-jp"]) == 0
    assert json.loads(user_registry_file().read_text())["victims"] == {"kitti-jp": str(directory.resolve())}
    assert main(["victims", "add-onnx", str(directory), "--name", "Dét"]) == 2
    err = capsys.readouterr().err
    assert "victim name 'Dét' must be lowercase letters, digits, '.', '_' or '-' (e.g. 'det')" in err
    with pytest.raises(RobustBenchError, match="victims add-onnx DIR --name NAME"):
        VICTIMS.resolve(str(directory))  # run --victims DIR


# ---- 7. UTF-8 byte-order marks ---------------------------------------------------------------
def test_bom_in_user_files_is_reported(tmp_path, cache, capsys):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    gt.mkdir()
    pred.mkdir()
    (gt / "000000.txt").write_text(LABEL, encoding="utf-8")
    (pred / "000000.txt").write_text(LABEL.rstrip("\n") + " 0.9\n", encoding="utf-8")
    assert main(["eval", "--gt", str(gt), "--pred", str(pred)]) == 0  # control: the same files without BOM
    capsys.readouterr()
    (gt / "000000.txt").write_text(LABEL, encoding="utf-8-sig")
    assert main(["eval", "--gt", str(gt), "--pred", str(pred)]) == 2
    assert f"robustbench3d: error: {gt / '000000.txt'}:1: {BOM}" in capsys.readouterr().err
    (gt / "000000.txt").write_text(LABEL, encoding="utf-8")
    split = tmp_path / "val.txt"
    split.write_text("000000\n", encoding="utf-8-sig")
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), "--split", str(split)]) == 2
    assert f"{split}:1: {BOM}" in capsys.readouterr().err

    calib = tmp_path / "calib.txt"
    calib.write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n", encoding="utf-8-sig")
    with pytest.raises(DataFormatError, match=re.escape(f"{calib}:1: {BOM}")):
        read_calibration(calib)

    directory = onnx_copy(tmp_path, "bom-onnx")
    manifest = directory / "manifest.json"
    manifest.write_bytes(b"\xef\xbb\xbf" + manifest.read_bytes())
    assert main(["victims", "add-onnx", str(directory)]) == 2
    assert f"{manifest}:1: {BOM}" in capsys.readouterr().err

    registry = cache / "victims" / "onnx.json"
    registry.parent.mkdir(parents=True)
    registry.write_text(json.dumps({"format": "robustbench3d.onnx_victims/1", "victims": {}}), encoding="utf-8-sig")
    proc = cli("victims", "list", "fpointnet-v1", cache=cache)
    assert proc.returncode == 0 and f"ignoring the ONNX victim registry: {registry}:1: {BOM}" in proc.stderr


# ---- 8. the user registry file is read on first use --------------------------------------------
def test_user_registry_file_is_read_on_first_lookup_not_at_import(cache):
    registry = cache / "victims" / "onnx.json"
    registry.parent.mkdir(parents=True)
    registry.write_text("{not json")
    code = ("import warnings; warnings.simplefilter('error'); "
            "import robustbench3d.victims.onnx.registration, robustbench3d.commands.victims_add_onnx; "
            "print('imported', flush=True); from robustbench3d.victims import VICTIMS; VICTIMS.names()")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={"PATH": "", "ROBUSTBENCH3D_CACHE": str(cache), "ROBUSTBENCH3D_NO_PLUGINS": "1"})
    assert proc.stdout == "imported\n"  # importing read nothing; the first lookup read the broken file
    assert proc.returncode != 0 and f"ignoring the ONNX victim registry: {registry}: not valid JSON" in proc.stderr

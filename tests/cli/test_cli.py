"""CLI behaviour: light start-up, clean errors, and the README/CI install staying in sync."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from robustbench3d.cli import main

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "onnxruntime", "onnx", "numpy", "PIL", "trimesh", "embreex", "scipy")


def test_help_imports_no_heavy_module() -> None:
    code = (
        "import sys; from robustbench3d.cli import build_parser; build_parser();"
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"heavy modules imported at CLI start-up: {out}"


def test_data_error_is_reported_without_traceback(tmp_path: Path, capsys) -> None:
    root = tmp_path / "ds"
    (root / "training" / "calib").mkdir(parents=True)
    (root / "training" / "calib" / "000000.txt").write_text("P0: 1 2\n")
    rc = main(["data", "stats", str(root), "--frames", "1"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "robustbench3d: error:" in err and "velodyne/000000.bin: file not found" in err


def _section(text: str, start: str, end: str) -> list[str]:
    body = text.split(start, 1)[1].split(end, 1)[0]
    return [line.strip() for line in body.splitlines() if line.strip() and not line.strip().startswith("#")]


def test_ci_installs_and_tests_exactly_as_readme_says() -> None:
    ci = (REPO / ".ci" / "run").read_text()
    readme = (REPO / "README.md").read_text()
    for start, end in (("# --- install (README \"Install\") ---", "# --- end install ---"),
                       ("# --- test (README \"Tests\") ---", "# --- end test ---")):
        for line in _section(ci, start, end):
            assert line in readme, f".ci/run line missing from README: {line}"

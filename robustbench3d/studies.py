"""The four files of a study directory (``tradeoff``, ``sweep``): ``NAME.json`` (the document), ``.csv``,
``.md`` and ``.png``, each written atomically, and the document read back with its kind checked.

Standard library only at module level (the caller builds the table, the markdown and the figure).
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_bytes, atomic_write_text


def figure_png(fig: Any, dpi: int) -> bytes:
    """A study's matplotlib figure as PNG bytes without a creation date (equal figures, equal bytes); closes it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def write_study(paths: Sequence[Path], doc: Mapping[str, Any], csv_text: str, markdown: str, png: bytes) -> list[Path]:
    """Write (json, csv, md, png) ``paths`` atomically, the JSON document indented by one; returns the paths."""
    json_path, csv_path, md_path, png_path = paths
    atomic_write_text(json_path, json.dumps(doc, indent=1, default=str) + "\n")
    atomic_write_text(csv_path, csv_text)
    atomic_write_text(md_path, markdown)
    atomic_write_bytes(png_path, png)
    return list(paths)


def read_study(path: Path, json_file: str, kind: str, command: str, keys: Sequence[str]) -> dict[str, Any]:
    """The ``json_file`` document of study directory ``path`` (or the file itself): a JSON object holding
    ``keys``; :class:`DataFormatError` naming the file (and the missing field) otherwise. ``kind`` names the
    document in errors ("sweep"), ``command`` the command that writes it."""
    p = path / json_file if path.is_dir() else path
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataFormatError(p, f"not found (write it with `robustbench3d {command} --out DIR`)") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise DataFormatError(p, f"not valid JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise DataFormatError(p, f"not a {kind} document")
    for key in keys:
        if key not in doc:
            raise DataFormatError(p, f"not a {kind} document", field=key)
    return doc

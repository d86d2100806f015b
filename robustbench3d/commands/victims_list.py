"""``robustbench3d victims list``: registered victims with their capabilities (table or JSON).

The origin column says where each came from: ``in-tree``, ``plugin <dist> <version>``, ``onnx
shipped`` or ``onnx user registry`` (``victims add-onnx``). Installed entry points that were
rejected (invalid names) are reported as warnings on stderr.
"""

from __future__ import annotations

import argparse
from typing import Any

from robustbench3d.listing import add_listing_arguments, print_listing


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_listing_arguments(parser)


def rows(pattern: str = "*") -> list[dict[str, Any]]:
    """One dict per registered victim (loads each entry; plugins that fail are reported)."""
    from robustbench3d.registry import RegistryError
    from robustbench3d.victims import VICTIMS

    out = []
    for name in VICTIMS.names(pattern):
        entry = VICTIMS.entry(name)
        try:
            info = VICTIMS.get(name).info
            out.append({"name": name, "origin": entry.origin, **info.as_dict(), "error": None})
        except RegistryError as exc:
            out.append({"name": name, "origin": entry.origin, "capabilities": None, "weights_sha256": None,
                        "summary": "", "error": str(exc)})
    return out


def victims_table(items: list[dict[str, Any]]) -> str:
    """One line per :func:`rows` item (no rule under the header)."""
    from robustbench3d.texttable import format_table

    header = ("name", "modalities", "backend", "gradients", "deterministic", "weights sha256", "origin", "summary")
    lines = []
    for r in items:
        cap = r["capabilities"]
        if cap is None:
            lines.append((r["name"], "-", "-", "-", "-", "-", r["origin"], f"ERROR: {r['error']}"))
            continue
        sha = r["weights_sha256"]
        lines.append((r["name"], "+".join(cap["modalities"]), cap["backend"], "yes" if cap["gradients"] else "no",
                      "yes" if cap["deterministic"] else "no", sha[:12] + "…" if sha else "none",
                      r["origin"], r["summary"]))
    return format_table(header, lines, rule=False)


def run(args: argparse.Namespace) -> int:
    from robustbench3d.victims import VICTIMS

    return print_listing(VICTIMS, rows(args.pattern), victims_table, args.json)

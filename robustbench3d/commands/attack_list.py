"""``robustbench3d attack list``: registered attacks with their parameters and requirements (table or JSON).

The companion of ``victims list``. The origin column says where each came from: ``in-tree`` (the
controls and the object-file attack), ``shipped object`` (the universal objects of the package's
manifest) or ``plugin <dist> <version>``. Parameters are the factory's keyword arguments, given on
the command line as ``NAME:KEY=VALUE``. Installed entry points that were rejected are reported as
warnings on stderr.
"""

from __future__ import annotations

import argparse
import inspect
from typing import Any

from robustbench3d.listing import add_listing_arguments, print_listing


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_listing_arguments(parser)  # the options of ``victims list``


def factory_parameters(factory: Any) -> list[str]:
    """The keyword parameters ``factory`` accepts, as ``name=default`` (``name`` when required);
    ``[]`` when its signature cannot be read."""
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return []
    keep = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [p.name if p.default is inspect.Parameter.empty else f"{p.name}={_short(p.default)}"
            for p in params if p.kind in keep]


def _short(value: Any) -> str:
    """A default as it is typed on the command line (floats to 6 significant digits)."""
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def rows(pattern: str = "*") -> list[dict[str, Any]]:
    """One dict per registered attack (loads each entry; plugins that fail are reported in ``error``)."""
    from robustbench3d.attacks import ATTACKS
    from robustbench3d.registry import RegistryError

    out = []
    for name in ATTACKS.names(pattern):
        entry = ATTACKS.entry(name)
        try:
            spec = ATTACKS.get(name)
        except RegistryError as exc:
            out.append({"name": name, "origin": entry.origin, "parameters": None, "requirements": None,
                        "summary": "", "error": str(exc)})
            continue
        out.append({"name": name, "origin": entry.origin, "parameters": factory_parameters(spec.factory),
                    "requirements": spec.requirements.as_dict(), "summary": spec.summary, "error": None})
    return out


def attacks_table(items: list[dict[str, Any]]) -> str:
    """One line per :func:`rows` item (no rule under the header)."""
    from robustbench3d.texttable import format_table

    header = ("name", "parameters", "needs", "origin", "summary")
    lines = []
    for r in items:
        if r["error"] is not None:
            lines.append((r["name"], "-", "-", r["origin"], f"ERROR: {r['error']}"))
            continue
        needs = [k.removeprefix("needs_") for k, v in r["requirements"].items() if v]
        lines.append((r["name"], ", ".join(r["parameters"]) or "-", "+".join(needs) or "-", r["origin"], r["summary"]))
    return format_table(header, lines, rule=False)


def run(args: argparse.Namespace) -> int:
    from robustbench3d.attacks import ATTACKS

    return print_listing(ATTACKS, rows(args.pattern), attacks_table, args.json)

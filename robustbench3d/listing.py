"""A registry's listing on the command line (``victims list``, ``attack list``): the options and the printing.

Standard library only.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from robustbench3d.registry import Registry


def add_listing_arguments(parser: argparse.ArgumentParser) -> None:
    """``--json`` and the name pattern."""
    parser.add_argument("--json", action="store_true", help="print a JSON list instead of a table")
    parser.add_argument("pattern", nargs="?", default="*", help="glob over names (default: all)")


def print_listing(registry: Registry[Any], items: list[dict[str, Any]], table: Callable[[list[dict[str, Any]]], str],
                  as_json: bool) -> int:
    """Print why each of ``registry``'s rejected entry points was ignored (warnings on stderr), then ``items``
    as JSON or ``table(items)`` on stdout; the exit status: 1 if an item failed to load (its ``error``), else 0.
    The ``run`` of ``victims list`` and ``attack list``."""
    for why in registry.rejected():
        print(f"robustbench3d: warning: {why}", file=sys.stderr)
    print(json.dumps(items, indent=2) if as_json else table(items))
    return 1 if any(r["error"] for r in items) else 0

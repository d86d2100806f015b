"""The one plain-text table layout of every command (standard library only).

Columns are padded to their widest cell and separated by two spaces; trailing spaces are
stripped. Callers turn their values into strings (the table never formats numbers).
"""

from __future__ import annotations

from collections.abc import Sequence


def format_table(header: Sequence[str], rows: Sequence[Sequence[str]], *, align: str | None = None,
                 rule: bool = True) -> str:
    """Header line, a dashed rule under it (unless ``rule`` is false), then one line per row.

    Args:
        header: column titles.
        rows: cells (strings), as many per row as ``header`` has.
        align: one letter per column, ``l`` (left, the default) or ``r`` (right).
        rule: draw the dashed line under the header.
    Raises:
        ValueError: a row or ``align`` of the wrong length, or an alignment other than l/r.
    """
    align = align if align is not None else "l" * len(header)
    if len(align) != len(header) or set(align) - {"l", "r"}:
        raise ValueError(f"align must be one of 'l'/'r' per column ({len(header)}), got {align!r}")
    for i, row in enumerate(rows):
        if len(row) != len(header):
            raise ValueError(f"row {i} has {len(row)} cells, the header {len(header)}")
    widths = [max([len(h), *(len(r[i]) for r in rows)]) for i, h in enumerate(header)]

    def line(values: Sequence[str]) -> str:
        return "  ".join(v.rjust(w) if a == "r" else v.ljust(w)
                         for v, w, a in zip(values, widths, align, strict=True)).rstrip()

    lines = [line(header)]
    if rule:
        lines.append(line(["-" * w for w in widths]))
    return "\n".join([*lines, *(line(r) for r in rows)])


__all__ = ["format_table"]

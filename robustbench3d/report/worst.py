"""The worst case: each victim ranked by its worst attacked headline AP, per proposal source.

Robustness leaderboards (RobustBench among them) rank a model by its accuracy under the strongest attack
evaluated against it; here that is the lowest headline AP (:data:`robustbench3d.metrics.HEADLINE`: Car BEV,
R40, moderate) over every *attack object* run against the victim with the same proposal source (an object trained
against a victim, an object file, an attack without an object: :func:`robustbench3d.report.data.role` ``attack``).
The clean cell and the controls (:data:`robustbench3d.report.data.CONTROLS`) are not attacks: they are shown for
reference and never enter the worst case.

Per (victim, proposal source) a :class:`WorstRow` holds the clean AP, the worst attacked AP with its interval,
the object(s) reaching it, its drop and relative drop against the clean cell (the run's ``attack_effect``, with
the paired bootstrap interval of the drop where recorded), the attack objects evaluated and those not (with why)
and the controls' APs. Rows are ranked by the worst attacked AP, highest (most robust) first; equal recorded APs
share a rank (``2=``); a victim with no attack object evaluated is unranked, last. A victim evaluated against
fewer attack objects than were run with its proposal source is flagged (:attr:`WorstCase.unequal`): its worst
case is over a smaller set, an upper bound on the worst over them all. Every missing number carries its reason.

Standard library only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

from robustbench3d.metrics import HEADLINE
from robustbench3d.report.data import CLEAN_ATTACK, NOT_RUN, RunCell, Section, cell_ci, role
from robustbench3d.results import CellResult

Interval = tuple[float, float]


@dataclass(frozen=True)
class Attacked:
    """One attack object's headline AP against a victim (an ``ok`` cell) and the cell it comes from."""

    object: str
    ap: float
    cell: RunCell


@dataclass(frozen=True)
class WorstRow:
    """One victim with one proposal source (module doc). ``clean``/``clean_note``: the clean cell's headline AP,
    or None and why; ``worst``: the attack objects reaching the lowest attacked AP (:attr:`worst_ap`; several on
    a tie, in run order, the drop properties the first's; empty: none evaluated); ``evaluated``: the attack
    objects with an AP against it; ``missing``: (object, why) for each attack object of the proposal source without one;
    ``controls``: (control, its AP or None, its status) in run order."""

    victim: str
    proposals: str
    clean: float | None
    clean_note: str
    worst: tuple[Attacked, ...]
    evaluated: tuple[str, ...]
    missing: tuple[tuple[str, str], ...]
    controls: tuple[tuple[str, float | None, str], ...]
    rank: int | None = None
    tied: bool = False

    @property
    def worst_ap(self) -> float | None:
        return self.worst[0].ap if self.worst else None

    @property
    def by(self) -> tuple[str, ...]:
        return tuple(a.object for a in self.worst)

    @property
    def source(self) -> RunCell | None:
        """The cell of the worst attacked AP (the first on a tie)."""
        return self.worst[0].cell if self.worst else None

    @property
    def flagged(self) -> bool:
        """Evaluated against fewer attack objects than were run with its proposal source."""
        return bool(self.missing)

    @property
    def worst_ci(self) -> Interval | None:
        """The recorded bootstrap interval of the worst attacked AP (percent), or None."""
        return None if self.source is None else cell_ci(self.source.cell, *HEADLINE[1:])

    def _effect(self, name: str) -> float | None:
        r = CellResult(self.source.cell) if self.source is not None else None
        if r is None or not r.effect:
            return None
        try:
            value = r.effect_value(name, *HEADLINE)
        except LookupError:
            return None
        return None if value is None else float(value)

    @property
    def drop(self) -> float | None:
        """Clean − worst attacked AP (points) as the run recorded it, or None (:attr:`drop_note`)."""
        return self._effect("drop")

    @property
    def relative_drop(self) -> float | None:
        """:attr:`drop` / clean AP (a fraction), or None (:attr:`drop_note`)."""
        return self._effect("relative_drop")

    @property
    def drop_ci(self) -> Interval | None:
        """The run's paired bootstrap interval of :attr:`drop` (points), or None."""
        if self.source is None:
            return None
        found = CellResult(self.source.cell).interval(*HEADLINE, table="drop_ci")
        if isinstance(found, Sequence) and len(found) == 2 and all(isinstance(v, int | float) for v in found):
            return float(found[0]), float(found[1])
        return None

    @property
    def drop_note(self) -> str:
        """Why there is no drop or relative drop ("" when both are there)."""
        if self.source is None:
            return "no attack object evaluated"
        if not CellResult(self.source.cell).effect:
            return "no clean cell to compare with"
        if self.drop is None:
            return "no drop recorded"
        return "clean AP 0" if self.relative_drop is None else ""


@dataclass(frozen=True)
class WorstCase:
    """The ranked :class:`WorstRow` of one proposal source and the attack objects run with it (in run order)."""

    proposals: str
    objects: tuple[str, ...]
    rows: tuple[WorstRow, ...]

    @property
    def unequal(self) -> str:
        """One line naming the victims evaluated against fewer attack objects than the others ("" if none)."""
        short = [r for r in self.rows if r.flagged]
        if not short:
            return ""
        names = ", ".join(f"{r.victim} ({len(r.evaluated)} of {len(self.objects)})" for r in short)
        verb = "was" if len(short) == 1 else "were"
        return (f"Not comparable as a ranking: {names} {verb} evaluated against fewer of the "
                f"{objects_text(len(self.objects))} run with {self.proposals} proposals than the others; a worst case "
                "over fewer attacks is only an upper bound on the worst over them all, so a flagged rank may be too "
                "high.")


def objects_text(n: int) -> str:
    """``1 attack object``, ``3 attack objects``."""
    return f"{n} attack object{'' if n == 1 else 's'}"


def _ap(rc: RunCell) -> float | None:
    try:
        return float(CellResult(rc.cell).ap(*HEADLINE))
    except LookupError:
        return None


def _status(rc: RunCell | None) -> str:
    if rc is None:
        return NOT_RUN
    r = CellResult(rc.cell)
    return r.status if not r.ok else "no BEV moderate AP"


def _row(victim: str, proposals: str, objects: Sequence[str], controls: Sequence[str],
         cells: Mapping[tuple[str, str], RunCell]) -> WorstRow:
    """The :class:`WorstRow` of ``victim`` (``cells``: its cells with ``proposals`` by (victim, attack))."""
    clean_rc = cells.get((victim, CLEAN_ATTACK))
    clean = None if clean_rc is None else _ap(clean_rc)
    clean_note = "" if clean is not None else "no clean cell" if clean_rc is None else f"clean cell {_status(clean_rc)}"
    attacked, missing = [], []
    for obj in objects:
        rc = cells.get((victim, obj))
        ap = None if rc is None else _ap(rc)
        if rc is None or ap is None:
            missing.append((obj, _status(rc)))
        else:
            attacked.append(Attacked(obj, ap, rc))
    low = min((a.ap for a in attacked), default=None)
    ctrl = tuple((name, _ap(rc), CellResult(rc.cell).status) for name in controls
                 if (rc := cells.get((victim, name))) is not None)
    return WorstRow(victim, proposals, clean, clean_note, tuple(a for a in attacked if a.ap == low),
                    tuple(a.object for a in attacked), tuple(missing), ctrl)


def ranked(rows: Sequence[WorstRow]) -> tuple[WorstRow, ...]:
    """``rows`` by worst attacked AP, highest first (equal APs by victim name, sharing the rank of the first:
    ``1, 2, 2, 4``); rows without a worst AP unranked, last, by victim name."""
    scored = sorted((r for r in rows if r.worst_ap is not None), key=lambda r: (-(r.worst_ap or 0.0), r.victim))
    out = []
    for r in scored:
        first = next(k for k, s in enumerate(scored) if s.worst_ap == r.worst_ap)
        out.append(replace(r, rank=first + 1, tied=sum(s.worst_ap == r.worst_ap for s in scored) > 1))
    return (*out, *sorted((r for r in rows if r.worst_ap is None), key=lambda r: r.victim))


def worst_cases(section: Section) -> list[WorstCase]:
    """The worst case of each proposal source of ``section`` that ran an attack object (in order of first
    appearance): every victim with a cell of that source, ranked (module doc)."""
    out = []
    for proposals in dict.fromkeys(CellResult(rc.cell).proposals for rc in section.cells):
        mine = [rc for rc in section.cells if CellResult(rc.cell).proposals == proposals]
        by_role = {k: list(dict.fromkeys(CellResult(rc.cell).attack for rc in mine if role(rc.cell) == k))
                   for k in ("control", "attack")}
        if not by_role["attack"]:
            continue
        cells = {(CellResult(rc.cell).victim, CellResult(rc.cell).attack): rc for rc in mine}
        victims = dict.fromkeys(CellResult(rc.cell).victim for rc in mine)
        rows = [_row(v, proposals, by_role["attack"], by_role["control"], cells) for v in victims]
        out.append(WorstCase(proposals, tuple(by_role["attack"]), ranked(rows)))
    return out

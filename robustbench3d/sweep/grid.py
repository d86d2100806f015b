"""The sweep's points: one universal object per family (icosphere level x radius) of one mode, named after its
parameters (``adv-texture-l3-r0.20``), and the benign sphere of each radius as its control.

The seed's point (:data:`~robustbench3d.attacks.object.DEFAULT_FAMILY`, ``l2-r0.40``: the shipped objects'
family) is always a point, added when ``--levels``/``--radii`` leave it out, and marked on every curve.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from robustbench3d.attacks.object import DEFAULT_FAMILY, LEVELS, RADIUS_RANGE, Family, check_family
from robustbench3d.errors import RobustBenchError

#: The modes a sweep trains (those of ``attack train``).
MODES = ("adv-shape", "adv-texture", "adv-object")
#: The benign control of the seed's radius keeps its registered name, so its cells are those of any run.
BENIGN = "benign-sphere"


@dataclass(frozen=True, order=True)
class Point:
    """One point of the sweep: the object of ``mode`` trained in ``family``."""

    level: int
    radius: float
    mode: str

    @property
    def family(self) -> Family:
        return Family(self.level, self.radius)

    @property
    def name(self) -> str:
        """The object's attack name and file stem: ``<mode>-l<level>-r<radius>``."""
        return f"{self.mode}-{self.family.name}"

    @property
    def file(self) -> str:
        """The object file, relative to the sweep directory."""
        return f"objects/{self.name}.ply"

    @property
    def seed_point(self) -> bool:
        """The shipped objects' family (``l2-r0.40``)."""
        return self.family == DEFAULT_FAMILY

    @property
    def vertex_colours(self) -> int:
        return self.family.n_vertices


def benign_name(radius: float) -> str:
    """The attack name of the grey undeformed sphere of ``radius`` m: ``benign-sphere`` at the seed's radius,
    ``benign-sphere-r0.20`` otherwise."""
    return BENIGN if round(radius, 2) == DEFAULT_FAMILY.radius else f"{BENIGN}-r{radius:.2f}"


def _items(text: str, option: str) -> list[str]:
    items = [t.strip() for t in text.split(",")]
    if not text.strip() or any(not t for t in items):
        raise RobustBenchError(f"{option} {text!r}: expected a comma-separated list, e.g. {option} "
                               + ("2,4" if option == "--levels" else "0.2,0.4,0.6"))
    dup = sorted({t for t in items if items.count(t) > 1})
    if dup:
        raise RobustBenchError(f"{option} {text!r}: {', '.join(dup)} listed twice")
    return items


def parse_levels(text: str) -> tuple[int, ...]:
    """``--levels 2,4`` -> (2, 4): icosphere levels of :data:`~robustbench3d.attacks.object.LEVELS`."""
    out = []
    for item in _items(text, "--levels"):
        try:
            level = int(item)
            check_family(level, DEFAULT_FAMILY.radius)
        except ValueError:
            raise RobustBenchError(f"--levels {text!r}: {item!r} is not an icosphere level; choose from "
                                   f"{', '.join(map(str, LEVELS))} (162, 642, 2562 vertex colours)") from None
        out.append(level)
    return tuple(sorted(out))


def parse_radii(text: str) -> tuple[float, ...]:
    """``--radii 0.2,0.4`` -> (0.2, 0.4): radii (m) in :data:`~robustbench3d.attacks.object.RADIUS_RANGE`,
    whole centimetres."""
    out = []
    lo, hi = RADIUS_RANGE
    for item in _items(text, "--radii"):
        try:
            radius = check_family(DEFAULT_FAMILY.level, float(item))[1]
        except ValueError:
            raise RobustBenchError(f"--radii {text!r}: {item!r} is not a radius in {lo:g}..{hi:g} m in whole "
                                   "centimetres (a roof object on a KITTI car roof)") from None
        if radius in out:
            raise RobustBenchError(f"--radii {text!r}: {radius:.2f} m listed twice")
        out.append(radius)
    return tuple(sorted(out))


def points(mode: str, levels: Sequence[int], radii: Sequence[float]) -> list[Point]:
    """Every (level, radius) of ``levels`` x ``radii`` plus the seed's point, ordered by level then radius."""
    if mode not in MODES:
        raise RobustBenchError(f"--mode {mode!r}: choose from {', '.join(MODES)}")
    fams = {(level, round(radius, 2)) for level in levels for radius in radii}
    fams.add((DEFAULT_FAMILY.level, DEFAULT_FAMILY.radius))
    return [Point(level, radius, mode) for level, radius in sorted(fams)]


def radii_of(pts: Sequence[Point]) -> list[float]:
    """The distinct radii of ``pts``, ascending."""
    return sorted({p.radius for p in pts})


__all__ = ["BENIGN", "MODES", "Point", "benign_name", "parse_levels", "parse_radii", "points", "radii_of"]

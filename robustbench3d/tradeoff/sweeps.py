"""Sweeps of the speed/accuracy trade: one knob at a time around the default setting.

A :class:`Setting` is everything a tradeoff cell depends on besides the frames: the victim (name and
factory arguments), the attack's render arguments and the scan's azimuth decimation. A :class:`Sweep`
varies one knob; its *reference* is its highest-fidelity value, against which every point's |ΔAP| is
measured. The ``frames`` sweep varies the number of evaluated frames and needs no cells of its own
(it re-scores the default setting's first N frames, :mod:`robustbench3d.tradeoff.analysis`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from robustbench3d.errors import RobustBenchError

#: The clean control every setting is also scored on (its AP drop needs it).
CLEAN = "none"


def _frozen(mapping: Mapping[str, Any] | None) -> tuple[tuple[str, Any], ...]:
    return tuple(sorted((mapping or {}).items()))


@dataclass(frozen=True)
class Setting:
    """What one tradeoff point runs (victim, attack render arguments, scan azimuth decimation).

    Attributes:
        victim: registered victim name.
        victim_args: its factory's keyword arguments (sorted (key, value) pairs).
        attack_args: keyword arguments of the attack's factory (render settings; not given to ``none``).
        decimation: keep every k-th azimuth column of each laser of the (attacked) scan; 1 keeps all.
    """

    victim: str
    victim_args: tuple[tuple[str, Any], ...] = ()
    attack_args: tuple[tuple[str, Any], ...] = ()
    decimation: int = 1

    def with_victim_arg(self, key: str, value: Any) -> Setting:
        return replace(self, victim_args=_frozen({**dict(self.victim_args), key: value}))

    def with_attack_arg(self, key: str, value: Any) -> Setting:
        return replace(self, attack_args=_frozen({**dict(self.attack_args), key: value}))

    def cell(self, attack: str, frames: int | None = None) -> CellSpec:
        """The cell of this setting under ``attack`` on the first ``frames`` frames (None: all; the clean control
        takes no attack arguments)."""
        return CellSpec(self.victim, self.victim_args, attack, () if attack == CLEAN else self.attack_args,
                        self.decimation, frames)


@dataclass(frozen=True)
class CellSpec:
    """One measured cell: a victim setting, an attack with its arguments, a scan decimation."""

    victim: str
    victim_args: tuple[tuple[str, Any], ...]
    attack: str
    attack_args: tuple[tuple[str, Any], ...]
    decimation: int
    frames: int | None = None  # the first N frames of the run only (None: all)

    @property
    def key(self) -> str:
        """Canonical text naming the cell (JSON; identical specs share one measurement)."""
        d = {"victim": self.victim, "victim_args": dict(self.victim_args), "attack": self.attack,
             "attack_args": dict(self.attack_args), "decimation": self.decimation}
        if self.frames is not None:
            d["frames"] = self.frames
        return json.dumps(d, sort_keys=True, separators=(",", ":"))


@dataclass(frozen=True)
class Point:
    """One value of a sweep's knob: its label and setting."""

    value: str
    setting: Setting


@dataclass(frozen=True)
class Sweep:
    """One knob's values; ``reference`` indexes the highest-fidelity point; ``frames``: the sweep is scored on
    the first N frames only (None: all), for a point too slow to run on all of them."""

    name: str
    knob: str
    points: tuple[Point, ...]
    reference: int
    notes: str = ""
    frames: int | None = None

    def cells(self, attack: str, default: Setting) -> list[CellSpec]:
        """The cells the sweep scores: each point's clean and attacked cell; the default setting's are the
        run's full cells (its first ``frames`` are used), the other points' cover only ``frames``."""
        out = []
        for p in self.points:
            n = None if p.setting == default else self.frames
            out += [p.setting.cell(CLEAN, n), p.setting.cell(attack, n)]
        return out

    def __post_init__(self) -> None:
        if not 0 <= self.reference < len(self.points):
            raise ValueError(f"sweep {self.name!r}: reference {self.reference} is not one of its points")


@dataclass(frozen=True)
class FrameSweep:
    """The ``frames`` sweep: the default setting scored on its first N frames, N in ``counts``."""

    counts: tuple[int, ...]
    name: str = "frames"
    knob: str = "frames evaluated"
    notes: str = field(default="the default setting scored on the first N frames of the same cells; reference: "
                                "all frames of the run")


#: Sweep names in table order (``--sweeps``).
SWEEP_NAMES = ("frames", "points", "azimuth", "input", "supersample", "precision", "backend", "render")
#: The ONNX twin of each victim with one (torch vs onnxruntime).
ONNX_TWINS = {"fpointnet-v1-lite": "fpointnet-v1-lite-onnx", "fpointnet-v1": "fpointnet-v1-onnx"}
#: Frame counts of the ``frames`` sweep (those below the run's frame count, then the run's).
FRAME_COUNTS = (10, 25, 50, 100, 200, 500)
#: Frames of the ``render`` sweep: the full-scene reference casts every ray of the scan at every face (about
#: 6 CPU-s per car on the 2-core VM, docs/tradeoff.md), so it runs on the first few frames only.
RENDER_FRAMES = 4
#: Frames of the ``precision`` sweep: bfloat16 autocast runs about 13x slower than float32 on CPUs without
#: native bfloat16 (AVX2), about 12 s per frame for the lite cascade there.
PRECISION_FRAMES = 12


@dataclass(frozen=True)
class VictimDefaults:
    """What the victim does without arguments: points per frustum and 2D input (W, H); None where the
    victim has no such knob (its sweep is left out)."""

    num_points: int | None = None
    input_size: tuple[int, int] | None = None
    precision: bool = False


def build_sweeps(victim: str, names: Sequence[str] = SWEEP_NAMES, frames: int = 50,
                 defaults: VictimDefaults | None = None) -> list[Sweep | FrameSweep]:
    """The sweeps ``names`` around ``victim``'s default setting (shipped weights, float32, trained point
    count and 2D input size, 3 x 3 camera samples, culled rendering, full azimuth density); victim sweeps
    only where ``defaults`` says the victim has the knob."""
    defaults = defaults or VictimDefaults()
    unknown = [n for n in names if n not in SWEEP_NAMES]
    if unknown:
        raise RobustBenchError(f"--sweeps: unknown sweep {unknown[0]!r}; choose from {', '.join(SWEEP_NAMES)}")
    base = Setting(victim)
    out: list[Sweep | FrameSweep] = []
    for name in SWEEP_NAMES:
        if name not in names:
            continue
        if name == "frames":
            out.append(FrameSweep((*[n for n in FRAME_COUNTS if n < frames], frames)))
        elif name == "points" and defaults.num_points is not None:
            native = defaults.num_points
            values = sorted({256, 512, 1024, 2048, native})
            out.append(Sweep(name, "points per frustum", tuple(
                Point(f"{n}" + (" (trained)" if n == native else ""),
                      base if n == native else base.with_victim_arg("num_points", n)) for n in values),
                reference=len(values) - 1, notes="reference: the most points"))
        elif name == "azimuth":
            ks = (1, 2, 4)
            out.append(Sweep(name, "LiDAR azimuth density", tuple(
                Point("1" if k == 1 else f"1/{k}", replace(base, decimation=k)) for k in ks), reference=0,
                notes="every k-th azimuth column of each laser kept, after the attack; reference: the full scan"))
        elif name == "input" and defaults.input_size is not None:
            w, h = defaults.input_size
            native = f"{w}x{h}"
            sizes = sorted({native, *(f"{round(w * f / 32) * 32}x{round(h * f / 32) * 32}" for f in (2 / 3, 4 / 3))},
                           key=lambda s: int(s.split("x")[0]))
            out.append(Sweep(name, "2D-stage input (px)", tuple(
                Point(s + (" (trained)" if s == native else ""),
                      base if s == native else base.with_victim_arg("input_size", s)) for s in sizes),
                reference=len(sizes) - 1, notes="reference: the largest input (the KITTI image is 1242 x 375)"))
        elif name == "supersample":
            ss = (1, 2, 3, 4)
            out.append(Sweep(name, "camera samples per pixel side", tuple(
                Point(f"{s}" + (" (default)" if s == 3 else ""),
                      base if s == 3 else base.with_attack_arg("supersample", s)) for s in ss),
                reference=len(ss) - 1, notes="reference: 4 x 4 samples per pixel"))
        elif name == "precision" and defaults.precision:
            ps = ("float64", "float32", "bfloat16")
            n = min(frames, PRECISION_FRAMES)
            out.append(Sweep(name, "frustum-stage precision", tuple(
                Point(p, base if p == "float32" else base.with_victim_arg("precision", p)) for p in ps),
                reference=0, frames=n, notes=f"reference: float64; on the first {n} frames (bfloat16's cost on "
                                             "CPUs without native bfloat16)"))
        elif name == "backend":
            twin = ONNX_TWINS.get(victim)
            if twin is None:
                continue
            out.append(Sweep(name, "inference backend", (Point("torch", base), Point("onnxruntime", Setting(twin))),
                             reference=0, notes=f"reference: torch; onnxruntime runs the exported twin {twin}"))
        elif name == "render":
            n = min(frames, RENDER_FRAMES)
            out.append(Sweep(name, "object rendering", (Point("culled", base),
                                                        Point("full scene", base.with_attack_arg("cull", False))),
                             reference=1, frames=n,
                             notes=f"full scene: every LiDAR ray of the pattern against every face, every pixel of "
                                   f"the image; reference: full scene; on the first {n} frames (its cost)"))
    return out


def cells_of(sweeps: Sequence[Sweep | FrameSweep], default: Setting, attack: str) -> list[CellSpec]:
    """Every distinct cell the sweeps need, the default setting's two first (the ``frames`` sweep needs only
    them)."""
    out = [default.cell(CLEAN), default.cell(attack)]
    for sweep in sweeps:
        if isinstance(sweep, Sweep):
            out += sweep.cells(attack, default)
    return list(dict.fromkeys(out))

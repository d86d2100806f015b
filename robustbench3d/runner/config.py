"""The configuration of a benchmark run and the identity of its cells."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.errors import RobustBenchError
from robustbench3d.eval.rules import TARGET_CLASS
from robustbench3d.victims.spec import PROPOSAL_SOURCES, describe_sources

#: Frames a ``robustbench3d run`` on the embedded ``val`` split evaluates by default: the first N ids
#: of the split (``--full``: all of them; ``--max-frames`` sets another N). The quick default: the
#: README's main job (12 cells, about 5.9 CPU-s per frame) in about 2 minutes on 2 cores with the data
#: cached; its price is the precision printed with each AP (95 % bootstrap half-width of BEV moderate
#: about 5 points at 25 frames, 2.5 at 100, 0.7 at all 1009; README "Results").
DEFAULT_VAL_FRAMES = 25


def default_max_frames(max_frames: int | None, full: bool, data: str | Path | None, split: str) -> int | None:
    """The ``max_frames`` of a run: ``max_frames`` if given, None (the whole split) with ``full`` or
    on a ``--data`` dataset or another split, else :data:`DEFAULT_VAL_FRAMES` (the embedded val split)."""
    if full and max_frames is not None:
        raise RobustBenchError("--full and --max-frames exclude each other: --full evaluates the whole split")
    if max_frames is not None or full or data is not None or split != "val":
        return max_frames
    return DEFAULT_VAL_FRAMES


def _unique(values: tuple[str, ...], what: str) -> None:
    if not values:
        raise RobustBenchError(f"--{what}: give at least one name")
    dup = sorted({v for v in values if values.count(v) > 1})
    if dup:
        raise RobustBenchError(f"--{what}: {', '.join(dup)} listed twice")


@dataclass(frozen=True)
class RunConfig:
    """Everything a ``robustbench3d run`` was asked to do.

    Attributes:
        victims: registered victim names, in table order.
        attacks: registered attack names.
        proposals: proposal sources, a subset of :data:`PROPOSAL_SOURCES` (:func:`describe_sources`).
        out: output directory.
        data: KITTI-layout dataset root, or None for the embedded dataset (generated if missing).
        split: split name (``ImageSets/<split>.txt``).
        max_frames: evaluate only the first N frames of the split (None: all).
        seed: run seed; attack randomness is drawn from (seed, frame id); passed as ``seed=`` to
            victim factories that declare a ``seed`` parameter (unless given in ``victim_args``).
        batch_size: frames per ``detect`` call.
        victim_args: per victim name, keyword arguments of its factory (e.g. ``weights``).
        attack_args: per attack name, keyword arguments of its factory.
        classes: evaluated classes.
        workers: processes generating the embedded dataset if it is missing.
        progress: progress bars on stderr.
        bootstrap: resamples of the bootstrap 95 % intervals over frames attached to every ok cell's AP
            (``metrics_ci``) and attack effect's drop (``drop_ci``); 0 disables them.
        force: replace finished cells of ``out`` computed with another configuration (without it the run
            refuses them before computing anything; :func:`~robustbench3d.runner.grid.run_benchmark`).
    """

    victims: tuple[str, ...]
    attacks: tuple[str, ...]
    proposals: tuple[str, ...]
    out: Path
    data: Path | None = None
    split: str = "val"
    max_frames: int | None = None
    seed: int = 0
    batch_size: int = 4
    victim_args: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    attack_args: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    classes: tuple[str, ...] = (TARGET_CLASS,)
    workers: int = 1
    progress: bool = True
    bootstrap: int = 1000
    force: bool = False

    def __post_init__(self) -> None:
        for what in ("victims", "attacks", "proposals"):
            object.__setattr__(self, what, tuple(getattr(self, what)))
            _unique(getattr(self, what), what)
        bad = [p for p in self.proposals if p not in PROPOSAL_SOURCES]
        if bad:
            raise RobustBenchError(f"--proposals: unknown source {bad[0]!r}; choose from {describe_sources()}")
        self._check_numbers()
        for what, args, names in (("victim", self.victim_args, self.victims),
                                  ("attack", self.attack_args, self.attacks)):
            extra = sorted(set(args) - set(names))
            if extra:
                raise RobustBenchError(f"--{what}-arg given for {', '.join(extra)}, which is not in --{what}s")
        object.__setattr__(self, "out", Path(self.out))
        if self.data is not None:
            object.__setattr__(self, "data", Path(self.data))

    def _check_numbers(self) -> None:
        """The numeric settings in the ranges of ``run``'s options (:mod:`robustbench3d.commands.run`)."""
        from robustbench3d.ranges import (
            BATCH_RANGE,
            FRAMES_RANGE,
            PROCESSES_RANGE,
            SEED_RANGE,
            check_bootstrap,
            check_range,
        )

        if self.max_frames is not None:
            check_range("--max-frames", self.max_frames, *FRAMES_RANGE, "frames")
        check_range("--batch-size", self.batch_size, *BATCH_RANGE, "frames per detect call")
        check_range("--seed", self.seed, *SEED_RANGE, "run seed")
        check_bootstrap(self.bootstrap)
        check_range("--workers", self.workers, *PROCESSES_RANGE, "dataset generation processes")

    def as_dict(self) -> dict[str, Any]:
        """JSON form (for provenance)."""
        return {"victims": list(self.victims), "attacks": list(self.attacks), "proposals": list(self.proposals),
                "out": str(self.out), "data": None if self.data is None else str(self.data), "split": self.split,
                "max_frames": self.max_frames, "seed": self.seed, "batch_size": self.batch_size,
                "victim_args": {k: dict(v) for k, v in self.victim_args.items()},
                "attack_args": {k: dict(v) for k, v in self.attack_args.items()},
                "classes": list(self.classes), "bootstrap": self.bootstrap}


@dataclass(frozen=True)
class CellKey:
    """One cell of the grid."""

    victim: str
    attack: str
    proposals: str

    @property
    def dirname(self) -> str:
        """Directory name under ``<out>/cells`` (registry names cannot contain ``+``)."""
        return f"{self.victim}+{self.attack}+{self.proposals}"

    def __str__(self) -> str:
        return f"{self.victim} / {self.attack} / {self.proposals}"


def grid(config: RunConfig) -> list[CellKey]:
    """Cells in table order: victims, then attacks, then proposal sources."""
    return [CellKey(v, a, p) for v in config.victims for a in config.attacks for p in config.proposals]


def fingerprint(cell_config: Mapping[str, Any]) -> str:
    """sha256 of the canonical JSON of a cell's configuration (sorted keys, no whitespace)."""
    text = json.dumps(cell_config, sort_keys=True, separators=(",", ":"), allow_nan=False, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


#: How :func:`config_differences` names some entries of a cell configuration (dotted paths).
_LABELS = {"dataset.frames": "frames (--max-frames)", "dataset.sha256": "labels sha256", "seed": "--seed",
           "batch_size": "--batch-size", "package_version": "package version", "dataset.root": "--data"}
_MISSING = object()


def _flatten(value: Any, path: str = "") -> dict[str, Any]:
    """Leaves of nested mappings by dotted path (a ``made_by`` record, an object's training log, is one leaf)."""
    if isinstance(value, Mapping) and value and not path.endswith("made_by"):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flatten(v, f"{path}.{k}" if path else str(k)))
        return out
    return {path: value}


def _label(path: str, labels: Mapping[str, str]) -> str:
    if path in labels:
        return labels[path]
    for prefix, option in (("victim.kwargs.", "--victim-arg "), ("attack.params.", "--attack-arg ")):
        if path.startswith(prefix):
            return option + path[len(prefix):]
    if path.endswith("made_by"):
        return "the object's made_by record"
    return "object sha256" if path.endswith("ply_sha256") else path


def _difference(label: str, a: Any, b: Any) -> str:
    """``"LABEL OLD vs NEW"``, or ``"LABEL differs"`` for records (mappings, lists) too long to show."""
    if any(isinstance(v, dict | list) and len(_text(v)) > 24 for v in (a, b)):
        return f"{label} differs"
    return f"{label} {_show(a)} vs {_show(b)}"


def _text(value: Any) -> str:
    if value is _MISSING:
        return "(none)"
    return value if isinstance(value, str) else json.dumps(value, sort_keys=True, default=str)


def _show(value: Any) -> str:
    """The value as text, shortened to 12 characters and an ellipsis past 24 (hashes, paths)."""
    text = _text(value)
    return text[:12] + "…" if len(text) > 24 else text


def _nested(path: str, flat: dict[str, Any]) -> bool:
    """True when ``path`` (an empty mapping on the other side) has entries in ``flat``: not a difference itself."""
    return path not in flat and any(other.startswith(f"{path}.") for other in flat)


def config_differences(old: Mapping[str, Any], new: Mapping[str, Any], limit: int = 3,
                       labels: Mapping[str, str] | None = None) -> str:
    """What differs between two cell configurations (:func:`~robustbench3d.runner.records.cell_config`), as
    ``"NAME OLD vs NEW; ..."`` for the first ``limit`` differing entries (long values shortened; ``labels``
    names entries by dotted path, over the run's names)."""
    names = {**_LABELS, **(labels or {})}
    a, b = (_flatten(json.loads(json.dumps(c, sort_keys=True, default=str))) for c in (old, new))  # as stored
    diff = [k for k in dict.fromkeys([*a, *b])
            if a.get(k, _MISSING) != b.get(k, _MISSING) and not _nested(k, a) and not _nested(k, b)]
    parts = [_difference(_label(k, names), a.get(k, _MISSING), b.get(k, _MISSING)) for k in diff[:limit]]
    if len(diff) > limit:
        parts.append(f"{len(diff) - limit} more")
    return "; ".join(parts) if parts else "no entry differs"


def refuse_changed_cells(out: Path, changed: list[tuple[str, str]], cell: str = "cell", done: str = "computed") -> None:
    """Raise the one-line refusal of finished cells of another configuration (written-once rule, without
    ``--force``): the first of ``changed`` (cell name, :func:`config_differences` text) named, the others
    counted; ``cell``/``done``: how the command calls its cells and their making. Nothing when ``changed`` is
    empty."""
    if not changed:
        return
    name, why = changed[0]
    more = f" (and {len(changed) - 1} more cell(s))" if len(changed) > 1 else ""
    raise RobustBenchError(f"--out {out}: finished {cell} {name}{more} was {done} with another configuration "
                           f"(on disk vs this run: {why}); pass --force to replace it, or choose another --out "
                           "(nothing was changed)")

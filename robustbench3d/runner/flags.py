"""Sanity flags of a run's cells: results that are computed correctly but should not be trusted blindly.

Each cell of ``summary.json`` carries ``flags``, a list of ``{"code", "message"}`` (empty when nothing is
suspicious), recomputed whenever the summary is written and printed by ``run``. Codes (docs/flags.md):

* ``attack-raises-ap``: the attacked cell's moderate BEV AP (R40, Car) is above its clean cell's by more
  than :data:`RAISE_TOL_AP` points (``attack_effect.drop`` below ``-RAISE_TOL_AP``).
* ``training-gradients``: the attack's object was trained with NaN or all-zero gradients, read from its
  ``made_by`` record (``attack train``'s sidecar) and the object itself: a recorded loss that is not a
  finite number; an attack loss term (``lidar``, ``image``; both are >= 0 and 0 only when no car gives a
  term) whose mean over the last 10 steps is exactly 0, i.e. no gradient from it in those steps; or an
  optimised parameter that never left its initial value (colours all the neutral grey, or vertices the
  template's: every step's gradient was zero).
* ``victim-nondeterministic``: two ``detect`` calls on the split's first frame (clean, this cell's proposal
  source) gave different detections as written to the result files (:func:`determinism`). Checked by the
  process that already holds the victim: with an executor, the worker of a cell's first shard right after
  that shard; without one, the run's process after its cells, on the victim they used. Once per victim x
  proposal source in that process; every cell of that victim x proposal source computed by the run is
  flagged if one of its checks found a difference (:func:`record_flags`). No victim is created for it.
* ``onnx-torch-divergence``: an ONNX victim's AP differs from its torch twin's (the victim named as
  ``source`` in the ONNX manifest, with the weights hash recorded there; same attack, proposals and
  dataset, both in the summary) by more than :class:`~robustbench3d.victims.onnx.parity.Tolerances`'
  ``ap_atol`` on some AP value.
* ``object-out-of-bounds``: a roof object's vertices leave its family's initial sphere's bounding box (+-radius:
  +-0.40 m for the default family, :data:`~robustbench3d.attacks.object.BOUNDS`;
  :attr:`~robustbench3d.attacks.object.Family.bounds`) by more than the object file's rounding tolerance.
* ``partial-split``: the cell was evaluated on fewer frames than its split has (``--max-frames``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robustbench3d.errors import RobustBenchError
from robustbench3d.results import CellResult, write_validated
from robustbench3d.runner.cell import RECORDED_SOURCES
from robustbench3d.runner.config import CellKey
from robustbench3d.runner.outcome import RunReport

if TYPE_CHECKING:
    from robustbench3d.attacks.base import Attack
    from robustbench3d.kitti.dataset import KittiDataset
    from robustbench3d.kitti.labels import Labels

ATTACK_RAISES_AP = "attack-raises-ap"
TRAINING_GRADIENTS = "training-gradients"
VICTIM_NONDETERMINISTIC = "victim-nondeterministic"
ONNX_TORCH_DIVERGENCE = "onnx-torch-divergence"
OBJECT_OUT_OF_BOUNDS = "object-out-of-bounds"
PARTIAL_SPLIT = "partial-split"
#: Every code, in the order a cell lists its flags.
CODES: tuple[str, ...] = (PARTIAL_SPLIT, ATTACK_RAISES_AP, OBJECT_OUT_OF_BOUNDS, TRAINING_GRADIENTS,
                          VICTIM_NONDETERMINISTIC, ONNX_TORCH_DIVERGENCE)
#: Codes that need the attack instance (kept from the cell file for cells whose attack this run lacks).
ATTACK_CODES = (OBJECT_OUT_OF_BOUNDS, TRAINING_GRADIENTS)
#: An attacked moderate BEV AP may exceed the clean one by this much (percentage points) unflagged.
RAISE_TOL_AP = 0.5
#: Attack loss terms of ``attack train`` (each >= 0, exactly 0 only when no car contributes).
ATTACK_TERMS = ("lidar", "image")

Flag = dict[str, str]


def flag(code: str, message: str) -> Flag:
    if code not in CODES:
        raise ValueError(f"unknown flag code {code!r}")
    return {"code": code, "message": message}


def partial_split(cell: Mapping[str, Any]) -> list[Flag]:
    """``partial-split`` when the cell saw fewer frames than its split has."""
    ds = CellResult(cell).dataset
    if ds["frames"] >= ds["split_frames"]:
        return []
    return [flag(PARTIAL_SPLIT, f"evaluated on {ds['frames']} of the {ds['split_frames']} frames of split "
                                f"{ds['split']!r} (--max-frames): AP of a slice, not of the split")]


def attack_raises_ap(cell: Mapping[str, Any], tol: float = RAISE_TOL_AP) -> list[Flag]:
    """``attack-raises-ap`` from the cell's ``attack_effect`` at the headline AP
    (:data:`robustbench3d.metrics.HEADLINE`: Car, BEV, R40, moderate)."""
    result = CellResult(cell)
    try:
        drop, clean = result.drop(), result.clean_ap()
    except LookupError:  # no comparison, or none at the headline AP
        return []
    if drop is None or drop >= -tol:
        return []
    return [flag(ATTACK_RAISES_AP, f"moderate BEV AP (R40) {clean - drop:.2f} % under attack is {-drop:.2f} points "
                                   f"above the clean cell's {clean:.2f} % (tolerance {tol}): an attack should not "
                                   "help the victim; check the attack, the clean cell and the frame count")]


def object_out_of_bounds(vertices: Any, tolerance_m: float | None = None, bounds: Any = None) -> list[Flag]:
    """``object-out-of-bounds`` for (V, 3) object-frame vertices (m) outside the initial sphere's box ``bounds``
    (half extents, m; default :data:`~robustbench3d.attacks.object.BOUNDS`, the default family's +-0.40 m)."""
    import numpy as np

    from robustbench3d.attacks.object import BOUNDS
    from robustbench3d.attacks.objectfile import BOUNDS_TOLERANCE_M

    tol = BOUNDS_TOLERANCE_M if tolerance_m is None else tolerance_m
    box = np.asarray(BOUNDS if bounds is None else bounds, dtype=np.float64)
    v = np.asarray(vertices, dtype=np.float64)
    excess = np.max(np.abs(v) - box, axis=1)
    outside = excess > tol
    if not outside.any():
        return []
    k = int(np.argmax(excess))
    return [flag(OBJECT_OUT_OF_BOUNDS, f"{int(outside.sum())} of {len(v)} vertices leave the initial sphere's "
                                       f"bounding box +-{float(box[0]):.2f} m (farthest: vertex {k} at "
                                       f"{tuple(round(float(x), 4) for x in v[k])}, {float(excess[k]):.4f} m "
                                       "outside): the object is larger than the attack's size constraint")]


def _numbers(record: Any, where: str) -> Iterable[tuple[str, Any]]:
    if isinstance(record, Mapping):
        for k, v in record.items():
            yield from _numbers(v, f"{where}.{k}")
    elif isinstance(record, list | tuple):
        for i, v in enumerate(record):
            yield from _numbers(v, f"{where}[{i}]")
    else:
        yield where, record


def training_gradients(made_by: Mapping[str, Any], vertices: Any = None, colors: Any = None,
                       family: Any = None) -> list[Flag]:
    """``training-gradients`` from an object's ``made_by`` record and, where given, its arrays (module doc) of
    the object :class:`~robustbench3d.attacks.object.Family` ``family`` (default: the default family).

    Objects that were not trained (no ``losses`` record: controls, hand-made files) get no flag.
    """
    losses = made_by.get("losses")
    if not isinstance(losses, Mapping):
        return []
    out: list[str] = []
    bad = [w for w, v in _numbers({k: losses.get(k) for k in ("first_step", "last_step", "mean_last_10")}, "losses")
           if v is not None and (isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v))]
    if bad:
        out.append(f"non-finite training loss at {', '.join(bad)}: its gradients were NaN or inf")
    last = losses.get("mean_last_10") or {}
    weights = losses.get("weights") or {}
    for term in ATTACK_TERMS:
        value = last.get(term) if isinstance(last, Mapping) else None
        if term in weights and isinstance(value, int | float) and value == 0:
            out.append(f"the {term} loss was exactly 0 in each of the last 10 training steps: the object got no "
                       f"{term} gradient (no car gave a term)")
    param = made_by.get("parametrisation") or {}
    import numpy as np

    from robustbench3d.attacks.object import DEFAULT_FAMILY, NEUTRAL_GREY, colors_to_file_precision, template_vertices

    if colors is not None and "sigmoid" in str(param.get("colour", "")):
        grey = colors_to_file_precision(np.full((1, 3), NEUTRAL_GREY))
        if np.array_equal(np.asarray(colors, dtype=np.float64), np.broadcast_to(grey, np.shape(colors))):
            out.append("the trained colours are all still the initial neutral grey: every colour gradient was 0")
    shape_trained = vertices is not None and "tanh" in str(param.get("shape", ""))
    if shape_trained and np.array_equal(np.asarray(vertices, dtype=np.float64),
                                        template_vertices(family or DEFAULT_FAMILY)):
        out.append("the trained vertices are still the undeformed sphere's: every shape gradient was 0")
    return [flag(TRAINING_GRADIENTS, "; ".join(out))] if out else []


def attack_flags(attack: Attack) -> list[Flag]:
    """``object-out-of-bounds`` and ``training-gradients`` of an attack that places a roof object."""
    from robustbench3d.attacks.object import RoofObject

    obj = getattr(attack, "obj", None)
    if not isinstance(obj, RoofObject):
        return []
    identity = getattr(attack, "identity", None) or {}
    return (object_out_of_bounds(obj.vertices(), bounds=obj.family.bounds)
            + training_gradients(identity, obj.vertices(), obj.colors, obj.family))


def determinism(victim: Any, proposals: str, kitti: KittiDataset, frame_id: str, gt: Labels,
                runs: int = 2) -> list[Flag]:
    """``victim-nondeterministic`` from ``runs`` ``detect`` calls on frame ``frame_id`` (clean; ``gt`` only
    feeds the GT-box sources, ``gt-object`` and ``gt-append`` with the clean control's nominal record), for the
    process that holds ``victim``. Never raises: a failing re-run is itself flagged (the victim has just worked
    through a cell)."""
    from robustbench3d.attacks.base import target_cars
    from robustbench3d.attacks.record import nominal_record
    from robustbench3d.kitti.labels import RESULT_PRECISION
    from robustbench3d.victims.base import victim_inputs

    texts = []
    try:
        for _ in range(runs):
            frame = kitti.lazy_frame(frame_id, gt)
            if proposals in RECORDED_SOURCES:  # the clean frame's record: the clean control's (nominal) one
                bare, given = victim_inputs([frame], [gt], proposals, objects=[nominal_record(frame, target_cars(gt))])
            else:
                bare, given = victim_inputs([frame], [gt], proposals)
            texts.append(victim.detect(bare, given)[0].to_text(RESULT_PRECISION))
    except Exception as exc:
        return [flag(VICTIM_NONDETERMINISTIC, f"the determinism re-run failed: {type(exc).__name__}: {exc}")]
    if all(t == texts[0] for t in texts):
        return []
    a, b = (t.splitlines() for t in texts[:2])
    first = next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))
    return [flag(VICTIM_NONDETERMINISTIC, f"two detect calls on frame {frame_id} (clean, proposals {proposals}) "
                                          f"gave different detections ({len(a)} and {len(b)} rows; first "
                                          f"difference at row {first + 1}): its AP may not reproduce")]


def probe_flags(value: Any) -> list[Flag] | None:
    """``value`` as a determinism verdict (a list of ``victim-nondeterministic`` flags, as :func:`determinism`
    returns and a shard record stores it), or None if it is not one."""
    if not isinstance(value, list):
        return None
    if not all(isinstance(f, dict) and set(f) == {"code", "message"} and f["code"] == VICTIM_NONDETERMINISTIC
               and isinstance(f["message"], str) and f["message"] for f in value):
        return None
    return [dict(f) for f in value]


def twin_source(victim: str) -> dict[str, Any] | None:
    """The ``source`` record (torch victim name, kwargs, weights sha256) of an ONNX victim's manifest, or None
    for a victim that is not a registered ONNX directory."""
    from robustbench3d.victims import VICTIMS
    from robustbench3d.victims.onnx.manifest import read_manifest

    factory = VICTIMS.get(victim).factory
    directory = getattr(factory, "directory", None)
    if not isinstance(directory, Path):
        return None
    return dict(read_manifest(directory).source)


def onnx_divergence(cells: Sequence[Mapping[str, Any]],
                    twin_of: Callable[[str], Mapping[str, Any] | None] = twin_source) -> dict[int, list[Flag]]:
    """``onnx-torch-divergence`` per index of ``cells`` (ok cells of ONNX victims whose twin cell is there)."""
    results = [CellResult(c) for c in cells]
    by_key = {r.id: r for r in results if r.ok}
    out: dict[int, list[Flag]] = {}
    for i, cell in enumerate(results):
        caps = cell.config["victim"].get("capabilities") or {}
        if not cell.ok or caps.get("backend") != "onnx":
            continue
        try:
            source = twin_of(cell.victim)
        except RobustBenchError:
            continue
        if not source:
            continue
        twin = by_key.get((source.get("victim"), cell.attack, cell.proposals))
        want_sha = source.get("weights_sha256")
        if twin is None or (want_sha and twin.config["victim"].get("weights_sha256") != want_sha):
            continue
        from robustbench3d.victims.onnx.parity import Tolerances  # loads torch: only for an ONNX cell with a twin

        atol = Tolerances().ap_atol
        mine, theirs = cell.result, twin.result
        assert mine is not None and theirs is not None  # both ok
        a = {v[:4]: v.ap for v in mine.values()}
        b = {v[:4]: v.ap for v in theirs.values()}
        deltas = {k: abs(a[k] - b[k]) for k in a if k in b}  # result order: the first of equal deltas wins
        if not deltas:
            continue
        worst = max(deltas, key=lambda k: deltas[k])
        if deltas[worst] > atol:
            out[i] = [flag(ONNX_TORCH_DIVERGENCE,
                           f"AP differs from its torch twin {source['victim']!r} by up to {deltas[worst]:.4f} points "
                           f"({'/'.join(worst)}: {a[worst]:.4f} vs {b[worst]:.4f}), beyond parity's ap_atol {atol}; "
                           f"see `robustbench3d victims parity {source['victim']} --onnx DIR`")]
    return out


def record_flags(report: RunReport, cells_dir: Path, attacks: Mapping[str, Attack], log: Callable[[str], None],
                 cell_file: str = "cell.json") -> None:
    """Set ``flags`` on every cell of ``report.summary`` (in place), rewrite the ``cell.json`` of each cell whose
    flags changed (atomically) and log every flag. The determinism verdict of a victim x proposal source is the
    one its computed cells brought back (:attr:`~robustbench3d.runner.outcome.CellOutcome.probe`; flagged if any
    check found a difference, the first such message in grid order); cells the run did not compute keep the
    flags that need what it lacks."""
    checked: dict[tuple[str, str], list[Flag]] = {}
    for o in report.outcomes:
        if not o.reused and CellResult(o.cell).ok and o.probe is not None:
            pair = (o.key.victim, o.key.proposals)
            if not checked.get(pair):
                checked[pair] = list(o.probe)
    computed = {o.key.dirname for o in report.outcomes if not o.reused}
    cells = report.summary
    divergent = onnx_divergence(cells)
    for i, cell in enumerate(cells):
        result = CellResult(cell)
        key = CellKey(*result.id)
        old = [dict(f) for f in result.flags]
        new = partial_split(cell) + attack_raises_ap(cell)
        if key.attack in attacks:
            new += attack_flags(attacks[key.attack])
        else:
            new += [f for f in old if f["code"] in ATTACK_CODES]
        if key.dirname in computed:
            new += checked.get((key.victim, key.proposals), []) if result.ok else []
        else:
            new += [f for f in old if f["code"] == VICTIM_NONDETERMINISTIC]
        new += divergent.get(i, [])
        new.sort(key=lambda f: CODES.index(f["code"]))
        if "flags" not in cell or new != old:
            cell["flags"] = new
            write_validated(cells_dir / key.dirname / cell_file, cell, cell_only=True)
        for f in new:
            log(f"flag {f['code']}: {key}: {f['message']}")


__all__ = ["CODES", "RAISE_TOL_AP", "attack_flags", "attack_raises_ap", "determinism", "flag", "object_out_of_bounds",
           "onnx_divergence", "partial_split", "probe_flags", "record_flags", "training_gradients", "twin_source"]

"""In-tree victims, registered with :func:`robustbench3d.victims.register_victim`.

Factories import torch only when called, so listing victims stays cheap. A victim with shipped
weights (:mod:`robustbench3d.victims.shipped`, ``weights/manifest.json``) loads them by default,
checked against the sha256 its registry entry declares. Otherwise pass ``weights=`` (a file written
by :meth:`~robustbench3d.victims.cascade.FPointNetCascade.save`) or the two trainers' outputs
(``yolo_weights=``, ``fpointnet_weights=``), or ``allow_untrained=True`` for plumbing tests.

Both cascades take the fidelity knobs of :mod:`robustbench3d.victims.cascade` (defaults: the
trained settings, results unchanged): ``num_points`` (points per frustum), ``input_size`` (the 2D
stage's "WxH") and ``precision`` ("float32", "bfloat16" or "float64"), e.g.
``--victim-arg fpointnet-v1-lite:num_points=1024 --victim-arg fpointnet-v1-lite:input_size=640x192``.

Every argument is checked before any weights load, each failure one line naming it: ``seed`` an
integer in :data:`SEED_RANGE`, ``gather`` one of :data:`GATHER_MODES`, ``precision`` one of
:data:`~robustbench3d.victims.cascade.PRECISIONS`, ``num_points`` in
:data:`~robustbench3d.victims.cascade.NUM_POINTS_RANGE`, ``input_size`` "WxH" with sides up to
:data:`~robustbench3d.victims.cascade.INPUT_SIDE_MAX` (multiples of the network's largest stride,
checked once the network is built).
"""

from __future__ import annotations

from collections.abc import Sequence
from numbers import Integral
from pathlib import Path
from typing import TYPE_CHECKING

from robustbench3d.errors import RobustBenchError
from robustbench3d.victims import VICTIMS, register_victim
from robustbench3d.victims.shipped import shipped, shipped_sha256
from robustbench3d.victims.spec import Capabilities

if TYPE_CHECKING:
    from robustbench3d.victims.cascade import FPointNetCascade
    from robustbench3d.victims.pointpillars.detector import PointPillarsDetector

CASCADE_CAPABILITIES = Capabilities(modalities=("camera", "lidar"), backend="torch", gradients=True,
                                    deterministic=True)
#: Range of the victim argument ``seed`` (also ``parity --seed``): any non-negative 64-bit signed integer.
#: numpy's ``default_rng`` refuses negative seeds (mid-run, at the first frustum) and torch's
#: ``manual_seed`` takes up to 2**64 - 1; int64 keeps the value exact in every JSON reader.
SEED_RANGE = (0, 2**63 - 1)
#: Object-point gather modes of the victim argument ``gather``.
GATHER_MODES = ("random", "topk")


def int_arg(key: str, value: object, lo: int, hi: int) -> int:
    """The victim argument ``key``: an integer (not a bool) in [lo, hi]; :class:`RobustBenchError`
    naming it otherwise."""
    if isinstance(value, bool) or not isinstance(value, Integral) or not lo <= int(value) <= hi:
        raise RobustBenchError(f"victim argument {key!r}: {value!r} is not an integer in [{lo}, {hi}]")
    return int(value)


def gather_arg(value: object) -> str:
    """The victim argument ``gather``: one of :data:`GATHER_MODES` (:class:`RobustBenchError` otherwise)."""
    if value not in GATHER_MODES:
        raise RobustBenchError(f"victim argument 'gather': {value!r} is not one of {', '.join(GATHER_MODES)}")
    return str(value)


def _check_cascade_args(seed: object, gather: object, precision: object, num_points: object,
                        input_size: object) -> None:
    """Check a cascade factory's arguments before any weights load (module doc)."""
    from robustbench3d.victims.cascade import PRECISIONS, parse_input_size, parse_num_points

    int_arg("seed", seed, *SEED_RANGE)
    gather_arg(gather)
    if precision not in PRECISIONS:
        raise RobustBenchError(f"victim argument 'precision': {precision!r} is not one of {', '.join(PRECISIONS)}")
    parse_num_points(num_points)
    parse_input_size(input_size, 1)  # the form and the bounds; the stride once the network is built


def _cascade(name: str, fpn_config: str, weights: str | Path | None, yolo_weights: str | Path | None,
             fpointnet_weights: str | Path | None, allow_untrained: bool, seed: int, gather: str,
             yolo_config: str = "mini") -> FPointNetCascade:
    from robustbench3d.victims.cascade import CascadeSettings, FPointNetCascade

    settings = CascadeSettings(seed=seed, gather=gather)  # type: ignore[arg-type]
    if weights is not None:  # the user's file: loaded as given (its hash goes into provenance)
        return FPointNetCascade.load(weights, settings)
    if yolo_weights is not None and fpointnet_weights is not None:
        return FPointNetCascade.from_parts(yolo_weights, fpointnet_weights, settings)
    if allow_untrained:
        return FPointNetCascade.untrained(fpn_config, yolo_config, seed=seed, settings=settings)
    ship = shipped(name)
    if ship is not None:
        ship.verify()
        return FPointNetCascade.load(ship.path, settings, sha256=VICTIMS.get(name).info.weights_sha256)
    others = [n for n in ("fpointnet-v1-lite", "fpointnet-v1") if n != name and shipped(n) is not None]
    raise RobustBenchError(
        f"victim {name!r} has no shipped weights"
        + (f" ({', '.join(others)} has)" if others else "")
        + ": pass weights=FILE (FPointNetCascade.save), yolo_weights= and fpointnet_weights= "
        "(outputs of `robustbench3d victims train-yolo|train-fpointnet`), or allow_untrained=True")


@register_victim("fpointnet-v1", capabilities=CASCADE_CAPABILITIES, weights_sha256=shipped_sha256("fpointnet-v1"),
                 summary="YOLO 2D stage -> Frustum-PointNet v1 (1024 pts), KITTI Car")
def fpointnet_v1(weights: str | Path | None = None, *, yolo_weights: str | Path | None = None,
                 fpointnet_weights: str | Path | None = None, allow_untrained: bool = False,
                 seed: int = 0, gather: str = "random", precision: str = "float32", num_points: int | None = None,
                 input_size: str | Sequence[int] | None = None) -> FPointNetCascade:
    """The F-PN v1 cascade with the full v1 network (§1.6; N = 1024). ``precision="bfloat16"`` runs the
    frustum stages of ``detect`` under bfloat16 autocast, ``"float64"`` on a float64 copy of the network
    (the 2D stage stays float32); ``num_points`` resamples frustums to N points; ``input_size`` ("WxH")
    sets the 2D stage's input (multiples of its largest stride)."""
    _check_cascade_args(seed, gather, precision, num_points, input_size)
    return _cascade("fpointnet-v1", "full", weights, yolo_weights, fpointnet_weights, allow_untrained, seed,
                    gather).with_precision(precision).with_num_points(num_points).with_input_size(input_size)


@register_victim("fpointnet-v1-lite", capabilities=CASCADE_CAPABILITIES,
                 weights_sha256=shipped_sha256("fpointnet-v1-lite"),
                 summary="mini3-YOLO 960x288 -> Frustum-PointNet v1 lite (512 pts, CPU config)")
def fpointnet_v1_lite(weights: str | Path | None = None, *, yolo_weights: str | Path | None = None,
                      fpointnet_weights: str | Path | None = None, allow_untrained: bool = False,
                      seed: int = 0, gather: str = "random", precision: str = "float32",
                      num_points: int | None = None, input_size: str | Sequence[int] | None = None) -> FPointNetCascade:
    """The cascade with the "lite" F-PN config (N = 512, global feature 256, seg head 128-64; shipped
    2D stage mini3 at 960x288). ``precision``, ``num_points`` and ``input_size`` as for
    :func:`fpointnet_v1`."""
    _check_cascade_args(seed, gather, precision, num_points, input_size)
    return _cascade("fpointnet-v1-lite", "lite", weights, yolo_weights, fpointnet_weights, allow_untrained,
                    seed, gather).with_precision(precision).with_num_points(num_points).with_input_size(input_size)


POINTPILLARS_CAPABILITIES = Capabilities(modalities=("lidar",), backend="torch", gradients=True, deterministic=True)


@register_victim("pointpillars", capabilities=POINTPILLARS_CAPABILITIES, weights_sha256=shipped_sha256("pointpillars"),
                 summary="PointPillars-style LiDAR-only detector (0.32 m pillars, centre head), KITTI Car")
def pointpillars(weights: str | Path | None = None, *, allow_untrained: bool = False, seed: int = 0,
                 score_threshold: float = 0.05, max_detections: int = 100) -> PointPillarsDetector:
    """The PointPillars-style victim (:mod:`robustbench3d.victims.pointpillars`): ``weights`` a ``model.pt`` of
    ``robustbench3d victims train-pointpillars`` (default: the shipped weights); ``score_threshold`` (lowest
    score kept) and ``max_detections`` (per frame) as in
    :func:`~robustbench3d.victims.pointpillars.glue.check_args`; ``seed`` initialises an untrained network."""
    from robustbench3d.victims.pointpillars.detector import PointPillarsDetector, load_pointpillars, untrained
    from robustbench3d.victims.pointpillars.glue import check_args

    options = check_args(score_threshold, max_detections)
    int_arg("seed", seed, *SEED_RANGE)
    if weights is not None:
        return PointPillarsDetector(load_pointpillars(weights), options)
    if allow_untrained:
        return PointPillarsDetector(untrained(int(seed)), options)
    ship = shipped("pointpillars")
    if ship is None:
        raise RobustBenchError("victim 'pointpillars' has no shipped weights: pass weights=FILE (model.pt of "
                               "`robustbench3d victims train-pointpillars`) or allow_untrained=True")
    ship.verify()
    return PointPillarsDetector(load_pointpillars(ship.path, sha256=VICTIMS.get("pointpillars").info.weights_sha256),
                                options)

"""The torch F-PN cascade an ONNX export or a parity check starts from: the ``VICTIM`` and ``--victim-arg``
options of ``victims export-onnx`` and ``victims parity``, checked before the victim is built.

Standard library only at module level.
"""

from __future__ import annotations

import argparse
from typing import Any


def check_int_option(option: str, value: int | None, lo: int, hi: int | None = None) -> None:
    """Refuse (:class:`RobustBenchError`, naming ``option``) an integer option outside [lo, hi] (hi None:
    no upper bound); None (not given) passes."""
    from robustbench3d.errors import RobustBenchError

    if value is not None and not (lo <= value and (hi is None or value <= hi)):
        bounds = f"in [{lo}, {hi}]" if hi is not None else f">= {lo}"
        raise RobustBenchError(f"{option}: {value} is out of range (an integer {bounds})")


def add_victim_arguments(parser: argparse.ArgumentParser) -> None:
    """VICTIM and --victim-arg (shared by ``victims export-onnx`` and ``victims parity``)."""
    parser.add_argument("victim", metavar="VICTIM",
                        help="registered torch victim: an F-PN cascade (e.g. fpointnet-v1) or pointpillars")
    parser.add_argument("--victim-arg", action="append", metavar="KEY=VALUE",
                        help="keyword argument of the victim's factory, e.g. weights=cascade.pt or "
                             "allow_untrained=true (repeatable; VALUE is JSON or a string)")


def check_factory_kwargs(name: str, kwargs: dict[str, Any]) -> None:
    """Refuse, before the victim is built, a ``--victim-arg`` key its factory does not take (one line
    listing the keys it does take; a factory with ``**kwargs`` takes any)."""
    import inspect

    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims import VICTIMS

    try:
        params = inspect.signature(VICTIMS.get(name).factory).parameters
    except (TypeError, ValueError):  # no readable signature: the factory call says
        return
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return
    takes = [k for k, p in params.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    unknown = sorted(set(kwargs) - set(takes))
    if unknown:
        raise RobustBenchError(f"--victim-arg {unknown[0]}=...: victim {name!r} takes no argument {unknown[0]!r} "
                               f"(it takes {', '.join(takes) or 'none'})")


def create_cascade(name: str, kwargs: dict[str, Any], pointpillars: bool = False) -> Any:
    """The registered victim ``name``, which must be an F-PN cascade (torch) or, with ``pointpillars``, the
    PointPillars detector (one graph, :mod:`robustbench3d.victims.onnx.pointpillars_export`)."""
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims import create_victim
    from robustbench3d.victims.cascade import FPointNetCascade
    from robustbench3d.victims.pointpillars.detector import PointPillarsDetector

    check_factory_kwargs(name, kwargs)
    victim = create_victim(name, **kwargs)
    if pointpillars and isinstance(victim, PointPillarsDetector):
        return victim
    if not isinstance(victim, FPointNetCascade):
        raise RobustBenchError(f"victim {name!r} is a {type(victim).__name__}; only F-PN cascades "
                               "(FPointNetCascade) can be exported per stage"
                               + (" (and PointPillars as one graph)" if pointpillars else ""))
    return victim

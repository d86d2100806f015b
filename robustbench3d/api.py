"""One Python call from a model to results: :func:`benchmark`.

    >>> import robustbench3d
    >>> df = robustbench3d.benchmark(my_detector, attacks=("none", "adv-object"), frames=25)   # doctest: +SKIP
    >>> df.query("metric == 'bev' and recall_points == 40 and difficulty == 'moderate'")     # doctest: +SKIP

The victim may be a registered name or any object with ``supported_proposals`` and
``detect(frames, proposals)`` (the contract of :class:`robustbench3d.victims.base.Detector`), registered
nowhere: it is registered under ``name`` for the call only and run in this process. The result is the
run's long-format ``results.csv`` (:data:`robustbench3d.results.CSV_COLUMNS`, one row per AP number) as
a pandas DataFrame; with ``out`` the run directory (cells, ``summary.json``, provenance) is kept there
and resumes as ``robustbench3d run`` does.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robustbench3d.errors import RobustBenchError

if TYPE_CHECKING:
    import pandas as pd

    from robustbench3d.victims.spec import Capabilities

#: The attacks :func:`benchmark` runs when none are named: the clean control and the shipped objects.
DEFAULT_ATTACKS: tuple[str, ...] = ("none", "benign-sphere", "adv-texture", "adv-object")


def _default_name(victim: Any) -> str:
    """A registry name from the victim's class name (``MyDetector`` -> ``user-mydetector``)."""
    return "user-" + (re.sub(r"[^a-z0-9]+", "-", type(victim).__name__.lower()).strip("-") or "victim")


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """One intra-op thread for the call, as ``run`` uses in every process (the same result files on any
    core count); the caller's thread settings are restored after."""
    from robustbench3d.runner.shards import THREAD_VARS, worker_setup

    saved_env = {k: os.environ.get(k) for k in THREAD_VARS}
    torch = sys.modules.get("torch")
    saved_threads = torch.get_num_threads() if torch is not None else None
    worker_setup()
    try:
        yield
    finally:
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        if torch is not None and saved_threads is not None:
            torch.set_num_threads(saved_threads)


def benchmark(victim: Any, attacks: Sequence[str] = DEFAULT_ATTACKS, frames: int | None = 25, *,
              proposals: Sequence[str] | None = None, name: str | None = None,
              capabilities: Capabilities | None = None, data: str | Path | None = None, split: str = "val",
              out: str | Path | None = None, seed: int = 0, batch_size: int = 4, bootstrap: int = 1000,
              victim_args: Mapping[str, Any] | None = None, progress: bool = False,
              force: bool = False) -> pd.DataFrame:
    """Score ``victim`` clean and under ``attacks`` on the first ``frames`` frames of ``split``.

    Args:
        victim: a registered victim name, or a detector object (see the module docstring).
        attacks: registered attack names or object files (``F.ply``); ``"none"`` (clean) is added when missing.
        frames: the first N frames of the split (None: all of them).
        proposals: proposal sources (default: ``detector`` and ``gt``, those the victim supports; the frustum
            protocols ``gt-object`` and ``gt-append`` when named).
        name: the name the object is run and reported under (default ``user-<class name>``).
        capabilities: what the object declares (default: its ``capabilities`` attribute, else camera+LiDAR,
            backend "other", no gradients, deterministic — checked by the runner's probe as for any victim).
        data, split: a KITTI-layout dataset and split (default: the embedded dataset, generated as needed).
        out: keep the run directory here (default: a temporary directory, removed after reading).
        seed, batch_size, bootstrap: as ``robustbench3d run``'s ``--seed``, ``--batch-size``, ``--bootstrap``.
        victim_args: keyword arguments of a registered victim's factory (names only).
        progress: progress bars and per-cell lines on stderr.
        force: replace finished cells of ``out`` computed with another configuration (``run --force``).
    Returns:
        the run's ``results.csv`` as a DataFrame.
    Raises:
        RobustBenchError: an object that is not a detector, a name already registered, bad arguments.
    """
    import pandas as pd

    from robustbench3d.attacks import ATTACKS
    from robustbench3d.runner import RunConfig, run_benchmark
    from robustbench3d.victims import VICTIMS
    from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

    registered: str | None = None
    if isinstance(victim, str):
        run_name, detector = victim, None
    else:
        if not callable(getattr(victim, "detect", None)) or not hasattr(victim, "supported_proposals"):
            raise RobustBenchError(f"benchmark: {type(victim).__name__} is not a detector: it needs "
                                   "supported_proposals and detect(frames, proposals)")
        if victim_args:
            raise RobustBenchError("benchmark: victim_args applies to a registered victim name, not an object")
        run_name, detector = name or _default_name(victim), victim
        if run_name in VICTIMS:
            raise RobustBenchError(f"benchmark: victim name {run_name!r} is already registered; pass name=")
        caps = capabilities or getattr(victim, "capabilities", None) or Capabilities(
            modalities=("camera", "lidar"), backend="other", gradients=False, deterministic=True)
        VICTIMS.register(run_name, VictimSpec(factory=lambda: detector,
                                              info=EntryInfo(caps, summary=f"benchmark(): {type(victim).__name__}")),
                         origin="benchmark()")
        registered = run_name
    try:
        if proposals is None:
            supported = (detector if detector is not None else VICTIMS.get(run_name).create(
                **dict(victim_args or {}))).supported_proposals
            proposals = tuple(p for p in ("detector", "gt") if p in supported) or tuple(supported)
        names, attack_args = ATTACKS.resolve_all(list(attacks), {})
        attack_list = tuple(names) if "none" in names else ("none", *names)
        with tempfile.TemporaryDirectory(prefix="rb3d-benchmark-") as tmp, _one_thread():
            target = Path(out) if out is not None else Path(tmp) / "run"
            config = RunConfig(victims=(run_name,), attacks=attack_list, proposals=tuple(proposals), out=target,
                               data=Path(data) if data is not None else None, split=split, max_frames=frames,
                               seed=seed, batch_size=batch_size,
                               victim_args={run_name: dict(victim_args)} if victim_args else {},
                               attack_args=attack_args,
                               progress=progress, bootstrap=bootstrap, force=force)
            run_benchmark(config, None if progress else (lambda _line: None))
            return pd.read_csv(target / "results.csv", keep_default_na=False, na_values=[""])
    finally:
        if registered is not None:
            VICTIMS.unregister(registered)

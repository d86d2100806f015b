"""What a cell's result depends on, as JSON records: victim, attack, evaluation, whole cell config.

The cell configuration (:func:`cell_config`) is hashed into the cell's fingerprint; a resumed run
reuses a finished cell only if the fingerprint is unchanged. Building the records loads the
registry entries but creates no victim (so an unchanged cell is reused without loading weights).
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

from robustbench3d import __version__
from robustbench3d.attacks import ATTACKS
from robustbench3d.attacks.base import Attack
from robustbench3d.kitti.labels import RESULT_PRECISION
from robustbench3d.provenance import weight_files
from robustbench3d.registry import RegistryError
from robustbench3d.results import SCHEMA_VERSION
from robustbench3d.runner.config import CellKey
from robustbench3d.victims import VICTIMS


def victim_kwargs(name: str, user_kwargs: Mapping[str, Any], seed: int) -> dict[str, Any]:
    """Factory keyword arguments: the user's, plus ``seed`` when the factory declares a ``seed``
    parameter and the user did not set it. A victim that cannot be loaded gets the user's only."""
    kwargs = dict(user_kwargs)
    try:
        factory = VICTIMS.get(name).factory
        params = inspect.signature(factory).parameters
    except (RegistryError, TypeError, ValueError):
        return kwargs
    if "seed" in params and "seed" not in kwargs:
        kwargs["seed"] = seed
    return kwargs


def victim_record(name: str, kwargs: Mapping[str, Any]) -> dict[str, Any]:
    """Name, registry origin, factory kwargs, capabilities and weights identities of a victim.

    ``weights_sha256`` is the registry entry's (shipped weights); ``weight_files`` hashes every
    kwarg naming an existing file (weights passed by the user). ``capabilities`` is None when the
    entry cannot be loaded (the cell then fails with the load error).
    """
    origin = VICTIMS.entry(name).origin
    try:
        info = VICTIMS.get(name).info
        capabilities: dict[str, Any] | None = info.capabilities.as_dict()
        registry_sha = info.weights_sha256
    except RegistryError:
        capabilities, registry_sha = None, None
    return {"name": name, "origin": origin, "kwargs": dict(kwargs), "capabilities": capabilities,
            "weights_sha256": registry_sha, "weight_files": weight_files(kwargs)}


def attack_record(name: str, params: Mapping[str, Any], attack: Attack) -> dict[str, Any]:
    """Name, registry origin, parameters, victim requirements and object description of an attack."""
    spec = ATTACKS.get(name)
    return {"name": name, "origin": ATTACKS.entry(name).origin, "params": dict(params),
            "requirements": spec.requirements.as_dict(), "object": attack.describe()}


def evaluation_record(classes: tuple[str, ...]) -> dict[str, Any]:
    from robustbench3d.eval.rules import EVALUATOR_VERSION, METRICS

    return {"evaluator": "robustbench3d.eval", "evaluator_version": EVALUATOR_VERSION, "classes": list(classes),
            "metrics": list(METRICS), "result_precision": RESULT_PRECISION}


def cell_config(key: CellKey, victim: dict[str, Any], attack: dict[str, Any], dataset: dict[str, Any],
                seed: int, batch_size: int, evaluation: dict[str, Any]) -> dict[str, Any]:
    """Everything the cell's numbers depend on (its sha256 is the cell fingerprint)."""
    return {"schema_version": SCHEMA_VERSION, "package_version": __version__, "victim": victim, "attack": attack,
            "proposals": key.proposals,
            "dataset": {k: dataset[k] for k in ("root", "split", "frames", "split_frames", "sha256", "embedded")},
            "seed": seed, "batch_size": batch_size, "evaluation": evaluation}

"""Victim models: the detectors under attack.

``VICTIMS`` is the registry (:class:`robustbench3d.registry.Registry` of
:class:`~robustbench3d.victims.spec.VictimSpec`). In-tree victims are declared in
:mod:`robustbench3d.victims.zoo` with :func:`register_victim`; installed packages add theirs
through the entry-point group ``robustbench3d.victims`` (an entry point names a ``VictimSpec``);
ONNX victim directories added with ``victims add-onnx`` come from
:mod:`robustbench3d.victims.onnx.registration`, which also resolves an ONNX victim directory given as
a reference (``run --victims DIR``: ``VICTIMS.resolve(DIR)``, :meth:`~robustbench3d.registry.Registry.resolve`).

    >>> from robustbench3d.victims import VICTIMS, create_victim
    >>> VICTIMS.names()                                   # doctest: +SKIP
    >>> victim = create_victim("fpointnet-v1", weights="runs/cascade")  # doctest: +SKIP

Importing this package does not import torch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from robustbench3d.registry import Registry
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

if TYPE_CHECKING:
    from robustbench3d.victims.base import Detector

ENTRY_POINT_GROUP = "robustbench3d.victims"

VICTIMS: Registry[VictimSpec] = Registry(
    "victim", group=ENTRY_POINT_GROUP, base=VictimSpec, key=lambda spec: spec.key,
    modules=("robustbench3d.victims.zoo",),
    loaders=("robustbench3d.victims.onnx.registration:register_user_victims",),
    path_resolvers=("robustbench3d.victims.onnx.registration:directory_reference",),
)

#: A factory ``(**kwargs) -> Detector``.
VictimFactory = TypeVar("VictimFactory", bound="Callable[..., Detector]")


def register_victim(name: str, *, capabilities: Capabilities, weights_sha256: str | None = None,
                    summary: str = "") -> Callable[[VictimFactory], VictimFactory]:
    """Decorator: register a factory ``(**kwargs) -> Detector`` under ``name`` with its metadata;
    the factory is returned unchanged."""
    info = EntryInfo(capabilities=capabilities, weights_sha256=weights_sha256, summary=summary)

    def decorator(factory: VictimFactory) -> VictimFactory:
        VICTIMS.register(name, VictimSpec(factory=factory, info=info))
        return factory

    return decorator


def create_victim(name: str, **kwargs: Any) -> Detector:
    """Build the registered victim ``name`` (kwargs go to its factory) and check that it honours
    the :mod:`~robustbench3d.victims.base` contract its capabilities declare."""
    return VICTIMS.get(name).create(**kwargs)


__all__ = ["ENTRY_POINT_GROUP", "VICTIMS", "create_victim", "register_victim"]

"""What the victim registry holds: :class:`VictimSpec`, a factory plus its metadata.

Standard library only, so ``robustbench3d.victims`` (and ``victims list``) import no numpy/torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from robustbench3d.registry import Spec


@dataclass(frozen=True)
class VictimSpec(Spec[Any]):
    """A factory returning a :class:`~robustbench3d.victims.base.Detector`, plus
    :class:`~robustbench3d.registry.EntryInfo` metadata. :meth:`create` checks the contract."""

    def create(self, **kwargs: Any) -> Any:
        from robustbench3d.victims.base import check_victim

        victim = self.factory(**kwargs)
        check_victim(victim, self.info.capabilities)
        return victim

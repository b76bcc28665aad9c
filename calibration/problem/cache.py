"""Every compile cache of the calibration, keyed by content, never by an object's identity.
"""

from __future__ import annotations

import collections
import json
from collections.abc import Callable, Hashable
from typing import Any

__all__ = ["CompileCache", "MODEL_FUNCTIONS", "BATCHES", "content_key"]


class CompileCache:
    """Compiled functions by a hashable content key, the least recently used dropped beyond
    ``size`` (each entry may hold a compiled rollout: they are large). ``get(key, build)``
    returns the entry of ``key``, built by ``build()`` on a miss; a key of None (a model with no
    content description) builds every time and keeps nothing."""

    def __init__(self, size: int):
        self.size = int(size)
        self._entries: collections.OrderedDict = collections.OrderedDict()

    def get(self, key: Hashable | None, build: Callable[[], Any]) -> Any:
        if key is None:
            return build()
        if key in self._entries:
            self._entries.move_to_end(key)
            return self._entries[key]
        value = build()
        self._entries[key] = value
        while len(self._entries) > self.size:
            self._entries.popitem(last=False)
        return value

    def __contains__(self, key) -> bool:
        return key in self._entries

    def __len__(self) -> int:
        return len(self._entries)


#: The ``ModelFunctions`` of each (configuration, observations, keys): few, each holds a compiled rollout.
MODEL_FUNCTIONS = CompileCache(4)


#: The compiled batches of sweeps and searches (a chunk shape in a mode, a search's vmapped
#: Jacobians), by ``content_key`` and the batch's description.
BATCHES = CompileCache(16)


def content_key(model) -> str | None:
    """The content key of a model (``calibration.problem.protocol.ResidualModel``): its fingerprint as
    canonical JSON (equal fingerprints: equal residuals, so one compilation serves both); None
    where it gives none."""
    fingerprint = model.fingerprint()
    return None if fingerprint is None else json.dumps(fingerprint, sort_keys=True, default=str)

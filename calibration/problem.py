"""A fit's objective built from where its data come from: a scene with measured profiles and a
front history, or experiment files (``jaxmpm.Experiment``) with theirs; several make one joint
objective. What ``python -m calibration fit`` and ``sweep`` fit."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from jaxmpm import Experiment

from .objective import CompositeObjective, FrontTarget, Objective
from .options import DataOptions

__all__ = ["member_objective", "objective_of"]


def member_objective(source, keys: Sequence[str], profiles=(), front=None,
                     options: DataOptions | None = None) -> Objective:
    """The objective of one ``source`` fitting ``keys`` to ``profiles`` and ``front`` (a
    ``FrontHistory``, a ``FrontTarget`` or None). ``source`` is a scene, whose blocks weigh
    ``options``' weights (1 where None), or a ``jaxmpm.Experiment``, whose [fit] table's
    weights and front correlation time ``options`` override where given
    (``Objective.from_experiment``)."""
    options = options or DataOptions()
    common = dict(front_threshold=options.front_threshold, jacobian=options.jacobian, weighting=options.weighting)
    if isinstance(source, Experiment):
        return Objective.from_experiment(source, keys, profile=list(profiles) or None, front=front,
                                         weights=options.weights(None),
                                         front_correlation_time=options.front_correlation_time, **common)
    if front is not None and options.front_correlation_time is not None:
        front = dataclasses.replace(FrontTarget.of(front), correlation_time=options.front_correlation_time)
    return Objective(source, keys, profile=list(profiles) or None, front=front, weights=options.weights(), **common)


def objective_of(sources: Sequence, keys: Sequence[str], data: Sequence[tuple], options: DataOptions | None = None,
                 *, shared: Sequence[str] | None = None, labels: Sequence[str] | None = None):
    """The objective fitting ``keys`` to ``data`` (one ``(profiles, front)`` pair per source)
    of ``sources`` (scenes or experiments, ``member_objective``). One source: its ``Objective``;
    several: one ``CompositeObjective`` whose members fit the same keys, or with ``shared`` those
    shared and the others per source, named ``key@label`` (``labels``, one per source)."""
    if len(sources) != len(data):
        raise ValueError(f"data: one (profiles, front) pair per source, got {len(data)} for {len(sources)}")
    members = [member_objective(source, keys, profiles, front, options)
               for source, (profiles, front) in zip(sources, data)]
    if len(members) == 1:
        return members[0]
    if shared is None:
        return CompositeObjective(members)
    return CompositeObjective.sharing(members, tuple(shared), labels)

"""A fit's objective built from where its data come from: a scene with measured profiles and a
front history, or experiment files (``jaxmpm.Experiment``) with theirs, or incline experiment
files (``calibration.data.incline``) with their flow-rule tables; several make one joint
objective. ``FitSetup`` is that description as data, which ``to_json`` and ``from_json`` record
in a fit's file so that a later command or another machine builds the same objective.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence
from typing import Any

from jaxmpm import Experiment

from ..data.flow_rule import flow_rule_keys, load_flow_rule
from ..data.incline import InclineExperiment, incline_from_text
from ..data.measurements import check_run_status, load_measurements
from .composite import CompositeObjective
from .flow_rule import FlowRuleObjective
from .objective import Objective
from .options import DataOptions
from .targets import FrontTarget

__all__ = ["FitSetup", "incline_objective", "member_objective", "objective_of"]


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


def incline_objective(incline: InclineExperiment, table, keys: Sequence[str], *, alone: bool = True,
                      dtype=None) -> FlowRuleObjective:
    """The ``FlowRuleObjective`` of an incline experiment's ``table`` (its material as the fixed
    values, between its side walls) fitting those of ``keys`` a flow rule fixes (μ1, μ2, I0; and μ_w
    between walls whose friction is "mu_w"): all of ``keys`` when it is fitted ``alone``, some of
    them in a joint fit; none is an error naming the file."""
    allowed = flow_rule_keys(incline.side_walls)
    own = tuple(k for k in keys if k in allowed)
    name = incline.path or incline.name
    if not own or (alone and len(own) < len(tuple(keys))):
        other = [k for k in keys if k not in allowed]
        raise ValueError(f"{name}: an incline's flow rule fits only {', '.join(allowed)}; it cannot fit "
                         f"{', '.join(other)}" + ("" if own else " (fit one of its keys, or leave the file out)"))
    return FlowRuleObjective(table, own, values=incline.material, dtype=dtype, side_walls=incline.side_walls)


def objective_of(sources: Sequence, keys: Sequence[str], data: Sequence, options: DataOptions | None = None,
                 *, shared: Sequence[str] | None = None, labels: Sequence[str] | None = None, dtype=None):
    """The objective fitting ``keys`` to ``data`` (one ``(profiles, front)`` pair per source,
    an incline's flow-rule table) of ``sources`` (scenes or experiments, ``member_objective``;
    incline experiments, ``incline_objective``, in ``dtype``). One source: its objective;
    several: one ``CompositeObjective`` whose members fit the same keys, or with ``shared`` those
    shared and the others per source, named ``key@label`` (``labels``, one per source)."""
    if len(sources) != len(data):
        raise ValueError(f"data: one (profiles, front) pair per source, got {len(data)} for {len(sources)}")
    alone = len(sources) == 1
    members = [incline_objective(source, datum, keys, alone=alone, dtype=dtype)
               if isinstance(source, InclineExperiment) else member_objective(source, keys, *datum, options)
               for source, datum in zip(sources, data)]
    if len(members) == 1:
        return members[0]
    if shared is None:
        return CompositeObjective(members)
    return CompositeObjective.sharing(members, tuple(shared), labels)


@dataclasses.dataclass(frozen=True)
class FitSetup:
    """What a fit's objective is built from. ``experiments``: one or more ``jaxmpm.Experiment``
    with their measurements or ``InclineExperiment`` with their flow-rule tables (which fit
    the keys among μ1, μ2, I0, and μ_w between walls whose friction is "mu_w", and read no
    ``options``); ``keys``: the fitted keys;
    ``options``: how the data are read and weighed; ``shared`` and ``labels``: with several
    experiments, the keys they share and the names of each one's own (``objective_of``);
    ``sort``, ``clip_noise``: how the measurement files are read (``load_profile``); ``dtype``:
    the float type the runs compute in (the caller enables it)."""

    experiments: tuple[Experiment | InclineExperiment, ...]
    keys: tuple[str, ...]
    options: DataOptions = DataOptions()
    shared: tuple[str, ...] | None = None
    labels: tuple[str, ...] | None = None
    sort: bool = False
    clip_noise: bool = False
    dtype: str = "float32"

    def measurements(self) -> list[tuple]:
        """Each experiment's (profiles, front history or None), read and checked: an experiment
        must list one measurement at least, and no file may come from a run that failed; an
        incline's flow-rule table (``load_flow_rule``)."""
        data = []
        for e in self.experiments:
            if isinstance(e, InclineExperiment):
                data.append(load_flow_rule(e.table_file))
                continue
            profiles, front = load_measurements(e, sort=self.sort, clip_noise=self.clip_noise)
            if not profiles and front is None:
                raise ValueError(f"{e.path or e.name}: lists no measurement ([[profile]] or [front])")
            check_run_status([*profiles, front])
            data.append((profiles, front))
        return data

    def stated_noise(self) -> dict[str, float]:
        """The noise the measurements state, by the objective's block: an incline table's relative
        σ (its header's ``noise``) for its "velocity" block; a collapse's profiles state none."""
        out = {}
        for i, e in enumerate(self.experiments):
            noise = load_flow_rule(e.table_file).noise if isinstance(e, InclineExperiment) else None
            if noise is not None:  # the block named as CompositeObjective names it: "label/velocity"
                prefix = "" if len(self.experiments) == 1 else f"{self.labels[i] if self.labels else i}/"
                out[f"{prefix}velocity"] = float(noise)
        return out

    def objective(self):
        """The objective (``objective_of``) of the experiments against their measurements."""
        return objective_of(self.experiments, self.keys, self.measurements(), self.options, shared=self.shared,
                            labels=self.labels, dtype=self.dtype)

    def to_json(self) -> dict[str, Any]:
        """The setup as JSON: each experiment as its file's text (``Experiment.to_toml``; an
        incline's as it was read, with ``"kind": "incline"``) and where that file was (its
        measurement files are found from there)."""
        return {"experiments": [_experiment_json(e) for e in self.experiments],
                "keys": list(self.keys), "options": dataclasses.asdict(self.options),
                "shared": None if self.shared is None else list(self.shared),
                "labels": None if self.labels is None else list(self.labels),
                "sort": self.sort, "clip_noise": self.clip_noise, "dtype": self.dtype}

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> FitSetup:
        """The setup ``to_json`` recorded (its measurement files must still be where they were)."""
        experiments = tuple(_experiment_of_json(e) for e in record["experiments"])
        tuple_or_none = lambda v: None if v is None else tuple(v)  # noqa: E731
        return cls(experiments, tuple(record["keys"]), DataOptions(**record["options"]),
                   tuple_or_none(record["shared"]), tuple_or_none(record["labels"]), bool(record["sort"]),
                   bool(record["clip_noise"]), str(record["dtype"]))


def _experiment_json(e) -> dict[str, Any]:
    path = None if e.path is None else str(e.path)
    if isinstance(e, InclineExperiment):
        if e.text is None:
            raise ValueError(f"{e.name}: an incline experiment not read from a file has no text to record")
        return {"kind": "incline", "toml": e.text, "path": path}
    return {"toml": e.to_toml(), "path": path}


def _experiment_of_json(record: dict[str, Any]):
    path = None if record["path"] is None else pathlib.Path(record["path"])
    if record.get("kind") == "incline":
        return incline_from_text(record["toml"], path)
    return Experiment.from_text(record["toml"], path)

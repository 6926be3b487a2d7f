"""The traffic kinds a scenario's ``[traffic].kind`` names, and how each builds its source.

This module stands above the scenario config and the SUMO package, whose builders it calls; the
traffic sources themselves (:mod:`twin.traffic`) know neither. A kind's builder imports what it
needs only when a source of that kind is built: synthetic traffic runs without importing a
simulator.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from twin.config import synthetic_source
from twin.errors import UserError
from twin.traffic.base import RecordedTraffic, TrafficSource


@dataclass(frozen=True)
class TrafficKind:
    """How a kind of traffic is built, and whether it is simulated per seed."""

    #: ``build(config, index, traffic_seed, separate_process, **options)``: the source of the
    #: ``index``-th seed (see :func:`build_traffic`)
    build: Callable[..., TrafficSource]
    #: simulated as its maps are pulled, once per seed; otherwise built once for all seeds
    live: bool = False


def _synthetic(config, index, traffic_seed, separate_process, **options) -> TrafficSource:
    return RecordedTraffic.from_source(synthetic_source(config))


def _sumo(config, index, traffic_seed, separate_process, **options) -> TrafficSource:
    from twin.sumo.scenario import live_source

    return live_source(config, index, traffic_seed, separate_process, **options)


KINDS: dict[str, TrafficKind] = {
    "synthetic": TrafficKind(_synthetic),
    "sumo": TrafficKind(_sumo, live=True),
}


def is_live_kind(kind: str) -> bool:
    """Whether traffic of ``kind`` is simulated once per seed (False for an unknown kind)."""
    known = KINDS.get(kind)
    return known is not None and known.live


def build_traffic(
    config,
    index: int = 0,
    traffic_seed: int | None = None,
    separate_process: bool = False,
    **options,
) -> TrafficSource:
    """The traffic source of a scenario config's ``index``-th seed. A live kind simulates it
    with seed ``traffic_seed + index`` (``traffic_seed`` defaults to the config's
    ``[traffic].seed``), in a process of its own with ``separate_process``; ``options`` go to
    the kind's builder (e.g. swapped-in files)."""
    kind = config.traffic.kind
    if kind not in KINDS:
        raise UserError(f"{config.path}: [traffic].kind = {kind!r} is not a traffic twin can run")
    return KINDS[kind].build(config, index, traffic_seed, separate_process, **options)

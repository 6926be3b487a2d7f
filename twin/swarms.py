"""The swarm registry: every swarm twin can run, by name, and how to build it.

The baselines come from :mod:`twin.policies`, the coordinated classical swarms from
:mod:`twin.planners` and :mod:`twin.tours`, the learned swarms from
:mod:`twin.learning.policies`. The registry stands above all of them; the learned swarms are
imported only when one is built, so that importing the registry loads no torch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from twin.errors import UserError
from twin.planners import PLANNERS
from twin.policies import GreedyPolicy, Policy, RandomPolicy, SweepingPolicy
from twin.tours import ToursPolicy


@dataclass(frozen=True)
class SwarmKind:
    """An entry of the swarm registry: how to build the swarm and what it is."""

    name: str
    build: Callable[..., Policy]  # keyword options -> a fresh policy
    summary: str
    learned: bool = False  # driven by a trained Q-network (needs torch and a checkpoint)


def _learned(name: str) -> Callable[..., Policy]:
    """Builder of a learned swarm; torch is imported only when one is built."""

    def build(**options) -> Policy:
        try:
            from twin.learning.policies import build_learned_swarm
        except ImportError as exc:
            raise UserError(
                f"swarm {name!r} needs {exc.name or 'an optional dependency'}: "
                "install twin with its learning dependencies (pip install twin)"
            ) from exc
        return build_learned_swarm(name, **options)

    return build


#: Every swarm twin can run, by name.
SWARMS: dict[str, SwarmKind] = {
    kind.name: kind
    for kind in (
        SwarmKind("random", RandomPolicy, "a uniform feasible action per drone"),
        SwarmKind("greedy", GreedyPolicy, "each drone to the cell of its view with the most I*T"),
        SwarmKind("sweeping", SweepingPolicy, "zig-zag sweepers plus greedy and random drones"),
        SwarmKind(
            "greedy-coordinated",
            PLANNERS["greedy-coordinated"],
            "greedy's I*T of the cell reached, collisions resolved by the coordinator",
        ),
        SwarmKind(
            "visit-gain",
            PLANNERS["visit-gain"],
            "the one-step gain of the visit at the next cell, by the coordinator",
        ),
        SwarmKind(
            "lookahead",
            PLANNERS["lookahead"],
            "the best visit gains over H steps plus the worth of the idleness left at the end, "
            "drones planned in turn, first moves by the coordinator",
        ),
        SwarmKind(
            "tours",
            ToursPolicy,
            "drones spaced evenly along closed tours over the cells worth patrolling",
        ),
        SwarmKind("rl", _learned("rl"), "the Q-network with the central coordinator", True),
        SwarmKind(
            "rl-decentralized",
            _learned("rl-decentralized"),
            "the Q-network, epsilon-greedy per drone on its own map",
            True,
        ),
        SwarmKind(
            "rl-online",
            _learned("rl-online"),
            "the coordinated Q-network that keeps learning every step",
            True,
        ),
    )
}


def available_policies() -> list[str]:
    """The names of the registered swarms, sorted."""
    return sorted(SWARMS)


def is_learned(name: str) -> bool:
    return name in SWARMS and SWARMS[name].learned


def check_swarm_name(name: str) -> None:
    """Raise :class:`UserError` naming the choices unless a swarm is registered as ``name``."""
    if name not in SWARMS:
        raise UserError(f"unknown swarm {name!r}; choose from {', '.join(available_policies())}")


def make_policy(name: str, **options) -> Policy:
    """Build the swarm registered under ``name``."""
    check_swarm_name(name)
    return SWARMS[name].build(**options)

"""The swarm registry: every swarm twin can run, by name, and how to build it.

The baselines come from :mod:`twin.policies`, the coordinated classical swarms from
:mod:`twin.planners`, :mod:`twin.tours` and :mod:`twin.nowcast_gain`, the learned swarms from
:mod:`twin.learning.policies`. The registry stands above all of them; the learned swarms are
imported only when one is built, so that importing the registry loads no torch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from twin.errors import UserError
from twin.nowcast_gain import NowcastGainPolicy
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
    #: plans on a history of earlier days (``twin run --history FILE`` hands it over)
    needs_history: bool = False


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
        SwarmKind(
            "nowcast-gain",
            NowcastGainPolicy,
            "the visit gain on its own nowcast plus the importance-weighted uncertainty the "
            "sighting removes, by the coordinator (needs --history)",
            needs_history=True,
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


#: ``rl@paper``: a learned swarm labelled, so that one run holds several of one kind (each with
#: its own checkpoint, e.g. the rows of a transfer matrix).
LABEL_SEPARATOR = "@"


def base_name(name: str) -> str:
    """The registered swarm of a (perhaps labelled) name: ``rl@paper`` -> ``rl``."""
    return name.split(LABEL_SEPARATOR, 1)[0]


def needs_history(name: str) -> bool:
    """Whether the swarm ``name`` plans on a history of earlier days."""
    base = base_name(name)
    return base in SWARMS and SWARMS[base].needs_history


def is_learned(name: str) -> bool:
    base = base_name(name)
    return base in SWARMS and SWARMS[base].learned


def check_swarm_name(name: str) -> None:
    """Raise :class:`UserError` naming the choices unless a swarm is registered as ``name``
    (a learned swarm may carry a label: ``rl@paper``)."""
    base, _, label = name.partition(LABEL_SEPARATOR)
    if base not in SWARMS:
        raise UserError(f"unknown swarm {name!r}; choose from {', '.join(available_policies())}")
    if LABEL_SEPARATOR in name:
        if not SWARMS[base].learned:
            raise UserError(
                f"swarm {name!r}: only learned swarms take a label (e.g. 'rl@paper'); use {base!r}"
            )
        if not label or not all(c.isascii() and (c.isalnum() or c in "-_.+=") for c in label):
            raise UserError(
                f"swarm {name!r}: the label after '@' must be letters, digits, '-', '_', '.', "
                "'+', '='"
            )


def check_swarm_list(swarms: list[str], known: Callable[[], list[str]] | None = None) -> None:
    """Raise :class:`ValueError` (a config model's validator turns it into one line naming the
    file and key) for an empty name, a swarm listed twice or an unknown swarm (``known``: the
    names offered instead, default every registered swarm)."""
    if any(not name.strip() for name in swarms):
        raise ValueError("has an empty name; remove it (list each swarm once, by name)")
    if len(set(swarms)) != len(swarms):
        raise ValueError("lists a swarm twice; list each once")
    for swarm in swarms:
        try:
            check_swarm_name(swarm)
        except UserError:
            offered = ", ".join((known or available_policies)())
            raise ValueError(f"has unknown swarm {swarm!r}; use {offered}") from None


def make_policy(name: str, **options) -> Policy:
    """Build the swarm registered under ``name`` (a labelled one under its base name)."""
    check_swarm_name(name)
    policy = SWARMS[base_name(name)].build(**options)
    if name != base_name(name):
        policy.name = name
    return policy


#: What run.json records of a learned swarm (``policies.<swarm>``), with the types.
POLICY_FIELDS: dict[str, object] = {
    "checkpoint": str,
    "sha256": str,
    "trained_epochs": int,
    "layers": list,
    "state": str,
    "history_runs": int,
    "history_seeds": list,
    "coordination": str,
    "eps": (int, float),
    "outages": list,
    "online": bool,
}


def check_policy_records(path, run: dict) -> None:
    """run.json's ``policies`` (``path``): records of the run's swarms (a complete run has one
    for each learned swarm and each planner that describes its options). A learned swarm's
    gives its checkpoint's sha256, epochs, layers that fit its state (13 paper inputs -> 5
    Q-values), a known state variant and coordination, and an epsilon in [0, 1]; a planner's
    passes its own ``check_record``."""
    import re

    from twin.grid import N_ACTIONS
    from twin.readback import RERUN, check_fields
    from twin.states import STATE_VARIANTS

    policies = run.get("policies")
    if policies is None:
        return
    if not isinstance(policies, dict):
        raise UserError(f"{path}: policies must be an object (swarm -> policy); {RERUN}")
    swarms = [s for s in run.get("swarms") or [] if isinstance(s, str)]
    for swarm, policy in policies.items():
        where = f"policies.{swarm}"
        if swarm not in swarms:
            raise UserError(f"{path}: {where}: {swarm!r} is no swarm of the run; {RERUN}")
        kind = SWARMS.get(base_name(swarm))
        if kind is not None and not _keeps_a_record(swarm):
            raise UserError(f"{path}: {where}: swarm {swarm!r} records no policy; {RERUN}")
        check_fields(path, policy, POLICY_FIELDS, where)
        if not is_learned(swarm):  # a planner records its own options, and checks them
            check_record = getattr(kind.build, "check_record", None) if kind else None
            if check_record is not None:
                try:
                    check_record(policy)
                except UserError as exc:
                    raise UserError(f"{path}: {where}: {exc}; {RERUN}") from None
            continue
        fixed = {"rl-online": ("online", True), "rl-decentralized": ("coordination",
                 "decentralized")}.get(base_name(swarm))  # fmt: skip
        if fixed is not None and policy.get(fixed[0]) not in (None, fixed[1]):
            raise UserError(
                f"{path}: {where}.{fixed[0]} = {repr(policy.get(fixed[0]))[:40]}, but swarm "
                f"{swarm!r} has {fixed[0]} = {fixed[1]!r} by its name; {RERUN}"
            )
        sha = policy.get("sha256")
        if sha is not None and not re.fullmatch(r"[0-9a-f]{64}", sha):
            raise UserError(f"{path}: {where}.sha256 = {sha[:40]!r} is no sha256; {RERUN}")
        epochs = policy.get("trained_epochs")
        if epochs is not None and epochs < 0:
            raise UserError(
                f"{path}: {where}.trained_epochs = {epochs} must be at least 0; {RERUN}"
            )
        state = policy.get("state")
        if state is not None and state not in STATE_VARIANTS:
            raise UserError(f"{path}: {where}.state = {state[:40]!r} is no state variant; {RERUN}")
        layers = policy.get("layers")
        if layers is not None:
            size = STATE_VARIANTS[state].size if state is not None else layers[:1]
            ok = (
                len(layers) >= 2
                and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in layers)
                and layers[-1] == N_ACTIONS
                and (state is None or layers[0] == size)
            )
            if not ok:
                raise UserError(
                    f"{path}: {where}.layers = {str(layers)[:40]} must run from the state's "
                    f"{size} inputs to {N_ACTIONS} Q-values; {RERUN}"
                )
        coordination = policy.get("coordination")
        if coordination is not None and coordination not in ("central", "decentralized"):
            raise UserError(
                f'{path}: {where}.coordination = {coordination[:40]!r} must be "central" or '
                f'"decentralized"; {RERUN}'
            )
        eps = policy.get("eps")
        if eps is not None and not 0 <= eps <= 1:
            raise UserError(f"{path}: {where}.eps = {eps} must be from 0 to 1; {RERUN}")
    if not run.get("partial"):
        missing = [s for s in swarms if s not in policies and _keeps_a_record(s)]
        if missing:
            raise UserError(f"{path}: no policies.{missing[0]} for the swarm; {RERUN}")


def _keeps_a_record(swarm: str) -> bool:
    """run.json records the policy of a learned swarm, and the options of a swarm that
    describes them."""
    kind = SWARMS.get(base_name(swarm))
    return kind is not None and (kind.learned or hasattr(kind.build, "describe"))

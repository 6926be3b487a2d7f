"""The patrol loop: several swarms side by side on one pass over a traffic source.

Each swarm keeps its own positions, idleness map and visited cells; all swarms see the same
``T^k``. Per step and swarm the loop records ``R^k`` (Def. 4, read on arrival), ``C^{k+1}``
(Def. 5) and the share of free cells visited so far.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from twin.grid import Grid
from twin.policies import Policy, SwarmView, Transition
from twin.scores import (
    ScoreParams,
    coverage,
    initial_idleness,
    rewards_on_arrival,
    update_idleness,
)
from twin.traffic.base import TrafficSource


@dataclass
class PatrolResult:
    """What one pass of several swarms over a traffic source produced."""

    swarms: list[str]
    grid: Grid
    seed: int
    rewards: np.ndarray  # (S, T): R^k, summed over drones
    coverage: np.ndarray  # (S, T): C^{k+1}
    visited_share: np.ndarray  # (S, T): share of free cells stood on up to step k+1
    positions: np.ndarray  # (S, T+1, N, 2): P_0 .. P_T
    importance: np.ndarray | None  # (T+1, nx, ny) float32, T^0 .. T^T
    seconds: float = 0.0
    completed_steps: int = 0
    error: str | None = None  # set when the source failed mid-run; arrays hold what was done
    extra: dict = field(default_factory=dict)

    @property
    def horizon(self) -> int:
        return self.rewards.shape[1]


def random_starts(grid: Grid, n_drones: int, rng: np.random.Generator) -> np.ndarray:
    """``n_drones`` distinct free cells drawn uniformly."""
    free = grid.free_cells()
    return free[rng.choice(len(free), size=n_drones, replace=False)]


def swarm_rng(seed: int, name: str) -> np.random.Generator:
    """A generator per (seed, swarm): a swarm's randomness does not depend on the others."""
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def run_patrol(
    source: TrafficSource,
    policies: Mapping[str, Policy],
    starts: np.ndarray,
    params: ScoreParams,
    seed: int = 0,
    progress: bool = False,
    keep_importance: bool = True,
) -> PatrolResult:
    """Run every swarm in ``policies`` from ``starts`` over the whole horizon of ``source``.

    If the source fails mid-run (a simulation crash), the result keeps the steps completed so
    far, truncated to them, and says why in ``error``.
    """
    grid, horizon = source.grid, source.horizon
    names = list(policies)
    n_swarms, n_drones = len(names), len(starts)
    starts = np.asarray(starts, dtype=np.int64)
    rewards = np.zeros((n_swarms, horizon))
    cover = np.zeros((n_swarms, horizon))
    visited_share = np.zeros((n_swarms, horizon))
    positions = np.zeros((n_swarms, horizon + 1, n_drones, 2), dtype=np.int64)
    importance = np.zeros((horizon + 1, *grid.shape), np.float32) if keep_importance else None

    views: list[SwarmView] = []
    visited = np.zeros((n_swarms, *grid.shape), dtype=bool)
    maps = source.importance_maps()
    t0 = time.perf_counter()
    bar = _progress_bar(source, horizon, progress)
    done, error = 0, None
    try:
        t_now = next(maps)
        if importance is not None:
            importance[0] = t_now
        for s, name in enumerate(names):
            policies[name].reset(grid, n_drones, swarm_rng(seed, name))
            views.append(
                _view(0, horizon, grid, starts.copy(), initial_idleness(grid), t_now, params)
            )
            visited[s, starts[:, 0], starts[:, 1]] = True
            positions[s, 0] = starts
        for k in range(horizon):
            t_next = next(maps)
            if importance is not None:
                importance[k + 1] = t_next
            for s, name in enumerate(names):
                policy, view = policies[name], views[s]
                actions = np.asarray(policy.act(view), dtype=np.int64)
                if not view.feasible[np.arange(n_drones), actions].all():
                    raise RuntimeError(f"swarm {name!r} chose an infeasible action at step {k}")
                nxt = grid.move(view.positions, actions)
                r = rewards_on_arrival(
                    grid, params, view.idleness, view.importance, t_next, view.positions, nxt
                )
                idle = update_idleness(view.idleness, nxt, grid, params.eta, params.delta)
                visited[s, nxt[:, 0], nxt[:, 1]] = True
                rewards[s, k] = r.sum()
                cover[s, k] = coverage(idle, grid)
                visited_share[s, k] = visited[s][grid.free].mean()
                positions[s, k + 1] = nxt
                views[s] = _view(k + 1, horizon, grid, nxt, idle, t_next, params)
                policy.learn(Transition(view, actions, r, views[s]))
            done = k + 1
            if bar is not None:
                bar.update(1)
                clock = source.clock(k + 1)
                if clock:
                    bar.set_postfix_str(clock, refresh=False)
    except StopIteration:
        error = f"traffic source ended after {done} of {horizon} steps"
    except Exception as exc:
        if not getattr(source, "keeps_partial_results", False):
            raise
        error = f"{type(exc).__name__}: {exc}"
    finally:
        if bar is not None:
            bar.close()
    result = PatrolResult(
        swarms=names,
        grid=grid,
        seed=seed,
        rewards=rewards[:, :done],
        coverage=cover[:, :done],
        visited_share=visited_share[:, :done],
        positions=positions[:, : done + 1],
        importance=None if importance is None else importance[: done + 1],
        seconds=time.perf_counter() - t0,
        completed_steps=done,
        error=error,
    )
    return result


def _view(k, horizon, grid, positions, idleness, importance, params) -> SwarmView:
    return SwarmView(
        k=k,
        horizon=horizon,
        grid=grid,
        positions=positions,
        idleness=idleness,
        importance=importance,
        feasible=grid.feasible_actions(positions),
        params=params,
    )


def _progress_bar(source: TrafficSource, horizon: int, enabled: bool):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=horizon, desc="patrol", unit="step", leave=False, dynamic_ncols=True)

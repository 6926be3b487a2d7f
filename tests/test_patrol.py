"""The one swarm step (twin.swarm) and the patrol loop built on it."""

from __future__ import annotations

import numpy as np
import pytest

from twin.grid import Grid
from twin.learning.data import random_swarm_episode
from twin.patrol import random_starts, run_patrol
from twin.scores import ScoreParams, rewards_on_arrival, update_idleness, visit_gain
from twin.swarm import InfeasibleActionError, initial_state, step
from twin.swarms import make_policy
from twin.traffic.base import RecordedTraffic
from twin.traffic.synthetic import Disturbance, SyntheticTraffic

PARAMS = ScoreParams(alpha_T=1.0, alpha_I=0.5)


def _source(horizon: int = 40) -> SyntheticTraffic:
    obstacles = np.zeros((8, 12), bool)
    obstacles[3, 4:7] = True
    obstacles[6, 9] = True
    grid = Grid(obstacles)
    disturbances = [Disturbance("big", 2, 3, 1.0, 2.0), Disturbance("small", 6, 8, 0.6, 1.5)]
    return SyntheticTraffic(grid, disturbances, horizon=horizon)


def _run(source, names=("random", "greedy", "sweeping"), seed=7):
    starts = random_starts(source.grid, 4, np.random.default_rng(seed))
    return run_patrol(source, {n: make_policy(n) for n in names}, starts, PARAMS, seed=seed)


def test_the_loop_pays_each_distinct_visited_cell_once():
    """R^k recomputed from the recorded paths: the visit gains of the distinct cells visited."""
    result = _run(_source())
    grid, imp = result.grid, result.importance.astype(np.float64)
    for s in range(len(result.swarms)):
        idle = grid.free.astype(float)
        for k in range(result.horizon):
            cells = {tuple(c) for c in result.positions[s, k + 1].tolist()}
            expected = sum(
                visit_gain(PARAMS.alpha_T * imp[k + 1][c] + PARAMS.alpha_I, idle[c], PARAMS)
                for c in cells
            )
            assert result.rewards[s, k] == pytest.approx(expected, rel=1e-6, abs=1e-9)
            idle = update_idleness(idle, result.positions[s, k + 1], grid, PARAMS.eta, PARAMS.delta)


def test_reward_parts_add_up_and_truth_defaults_to_none():
    result = _run(_source(20))
    shape = (3, 20)
    for a in (result.reward_importance, result.reward_idleness, result.reward_paper):
        assert a.shape == shape and np.isfinite(a).all()
    np.testing.assert_allclose(
        result.reward_importance + result.reward_idleness, result.rewards, rtol=1e-12
    )
    assert result.truth is None and result.importance.shape == (21, 8, 12)


def test_one_drone_the_paper_accounting_telescopes_to_the_headline():
    """One drone: summed over the run, Def. 4 as printed is the headline plus the end terms
    ``F(P_T, I^T, T^T) - F(P_0, I^0, T^0)``, ``F(p, I, T) = sum_{Adj(p)} (alpha_T T + alpha_I) I``."""
    source = _source(15)
    starts = np.array([[0, 0]])
    result = run_patrol(source, {"greedy": make_policy("greedy")}, starts, PARAMS, seed=1)
    grid, imp = result.grid, result.importance.astype(np.float64)
    idle = grid.free.astype(float)
    for k in range(result.horizon):
        idle = update_idleness(idle, result.positions[0, k + 1], grid, PARAMS.eta, PARAMS.delta)

    def f(p, idleness, t):
        return grid.sum_in_view((PARAMS.alpha_T * t + PARAMS.alpha_I) * idleness, p)[0]

    ends = f(result.positions[0, -1], idle, imp[-1]) - f(starts, grid.free_float, imp[0])
    assert result.reward_paper.sum() == pytest.approx(result.rewards.sum() + ends, rel=1e-6)


def test_a_source_that_ends_early_keeps_the_steps_done():
    full = _source(10)
    maps = np.stack(list(full.importance_maps()))

    class Short(RecordedTraffic):
        def importance_maps(self):
            yield from self.maps[:6]  # T^0 .. T^5 of a horizon of 10

    result = _run(Short(full.grid, maps))
    assert result.completed_steps == 5 and "ended after 5 of 10" in result.error
    assert result.rewards.shape == result.reward_paper.shape == (3, 5)
    assert result.positions.shape[1] == 6


def test_step_matches_the_reward_and_rejects_infeasible_actions():
    source = _source(3)
    grid, maps = source.grid, list(source.importance_maps())
    state = initial_state(grid, np.array([[0, 0], [2, 5]]), maps[0])
    assert state.visited.sum() == 2 and state.feasible.tolist()[0] == [1, 0, 1, 0, 1]
    nxt, out = step(state, np.array([4, 0]), maps[1], grid, PARAMS)
    expected = rewards_on_arrival(
        grid, PARAMS, state.idleness, maps[0], maps[1], state.positions, nxt.positions
    )
    np.testing.assert_array_equal(out.rewards, expected)
    assert nxt.k == 1 and nxt.positions.tolist() == [[0, 1], [2, 5]]
    assert nxt.visited.sum() == 3 and state.visited.sum() == 2  # the old state is untouched
    np.testing.assert_array_equal(out.feasible, grid.feasible_actions(nxt.positions))
    with pytest.raises(InfeasibleActionError, match=r"drone 1 at \(2, 5\): action 2 \(down\)"):
        step(nxt, np.array([0, 2]), maps[2], grid, PARAMS)  # (3, 5) is an obstacle
    with pytest.raises(InfeasibleActionError, match=r"not one of 0\.\.4"):
        step(nxt, np.array([0, 7]), maps[2], grid, PARAMS)
    with pytest.raises(InfeasibleActionError, match="one per drone"):
        step(nxt, np.array([0]), maps[2], grid, PARAMS)


def test_random_swarm_episode_follows_the_step():
    source = _source(12)
    ep = random_swarm_episode(source, 3, PARAMS, np.random.default_rng(4))
    grid, maps = source.grid, list(source.importance_maps())
    # replay the recorded actions through the step from the recorded start
    start = np.rint(ep.states[0, :, :2] * [grid.nx, grid.ny]).astype(np.int64)
    state = initial_state(grid, start, maps[0])
    for k in range(source.horizon):
        state, out = step(state, ep.actions[k], maps[k + 1], grid, PARAMS)
        np.testing.assert_allclose(ep.rewards[k], out.rewards, rtol=1e-6)
        np.testing.assert_array_equal(ep.next_feasible[k], out.feasible)


def test_a_tiny_beta1_dissipates_at_once_without_a_warning():
    """``beta1 = 1e-310``: ``-k / (beta1 T)`` overflows to -inf, so a big disturbance is gone
    after step 0, silently (a bare "overflow encountered in divide" notice named no key;
    probe 16's f07)."""
    import warnings

    big = Disturbance(kind="big", i=1, j=1, amplitude=1.0, sigma=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a = big.amplitudes(np.arange(5), 20, 1e-310, 0.5)
    assert a.tolist() == [1.0, 0.0, 0.0, 0.0, 0.0]


def test_a_map_that_fades_at_once_says_so_in_synthetic_words(tmp_path, capsys):
    """A synthetic map whose one disturbance fades within a step: the notice that nothing is
    left to see names the synthetic cause, and counts from step 1 (probe 16's P2-f07)."""
    from twin.cli import main

    config = tmp_path / "b.toml"
    config.write_text(
        '[grid]\nnx = 6\nny = 6\n[traffic]\nkind = "synthetic"\nhorizon = 20\nbeta1 = 1e-310\n'
        'disturbances = [{ kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 1.0 }]\n'
    )
    code = main(["evaluate", "--config", str(config), "--seeds", "1", "--swarms", "random",
                 "--no-ceiling", "--no-report", "--quiet", "--out", str(tmp_path / "r")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0 and "importance is 0 in every cell from step 1 on" in err, err
    assert "synthetic disturbances that fade within a step" in err

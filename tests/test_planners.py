"""Coordinated classical swarms (twin.planners): collision-free, exact, reproducible."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.errors import UserError
from twin.grid import ACTION_DELTAS, Grid
from twin.patrol import random_starts
from twin.planners import LookaheadPolicy, VisitGainPolicy, action_paths
from twin.policies import SwarmView
from twin.scores import ScoreParams, update_idleness, visit_gain
from twin.swarms import available_policies, make_policy

COORDINATED = ("greedy-coordinated", "visit-gain", "lookahead")
PARAMS = ScoreParams()


def make_view(grid, positions, idleness, importance, k=0, params=PARAMS) -> SwarmView:
    return SwarmView(
        k=k,
        horizon=100,
        grid=grid,
        positions=positions,
        idleness=idleness,
        importance=importance,
        feasible=grid.feasible_actions(positions),
        params=params,
    )


def scene(seed, nx, ny, n, obstacle_share):
    rng = np.random.default_rng(seed)
    obstacles = rng.random((nx, ny)) < obstacle_share
    if (~obstacles).sum() < n:
        obstacles[:] = False
    grid = Grid(obstacles)
    positions = random_starts(grid, min(n, grid.n_free), rng)
    idleness = rng.random(grid.shape) * grid.free
    return rng, grid, positions, idleness


def run(policy, rng, grid, positions, idleness, steps, params=PARAMS):
    """Drive ``policy`` for ``steps`` steps on random importance maps; yield each step."""
    policy.reset(grid, len(positions), np.random.default_rng(rng.integers(1 << 32)))
    for k in range(steps):
        importance = rng.random(grid.shape) ** 3 * grid.free
        view = make_view(grid, positions, idleness, importance, k, params)
        actions = policy.act(view)
        yield view, actions
        positions = grid.move(positions, actions)
        idleness = update_idleness(idleness, positions, grid, params.eta, params.delta)


def test_registered():
    assert set(COORDINATED) <= set(available_policies())
    assert make_policy("lookahead", horizon=3).horizon == 3


@pytest.mark.parametrize("horizon, beam", [(0, 20), (6, 0), (17, 20), (2.5, 20), (True, 0)])
def test_lookahead_rejects_bad_horizon(horizon, beam):
    """The full tree (``beam = 0``) stops at H = 5, the beam search at 16."""
    with pytest.raises(UserError, match="horizon"):
        make_policy("lookahead", horizon=horizon, beam=beam)


@pytest.mark.parametrize("name", COORDINATED)
@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    nx=st.integers(2, 8),
    ny=st.integers(2, 8),
    n=st.integers(2, 10),
    obstacle_share=st.floats(0.0, 0.4),
)
def test_no_two_drones_ever_share_a_cell(name, seed, nx, ny, n, obstacle_share):
    rng, grid, positions, idleness = scene(seed, nx, ny, n, obstacle_share)
    n = len(positions)
    for view, actions in run(make_policy(name), rng, grid, positions, idleness, steps=12):
        assert view.feasible[np.arange(n), actions].all()
        nxt = grid.move(view.positions, actions)
        assert len(np.unique(nxt[:, 0] * grid.ny + nxt[:, 1])) == n


def visit_gain_objective(view, joint) -> float:
    """Sum of ``(alpha_T T + alpha_I)(min(1, I + delta) - eta I)`` over the cells reached,
    computed cell by cell from the maps, independently of the policy's code."""
    p, total = view.params, 0.0
    for (i, j), u in zip(view.positions, joint, strict=True):
        a, b = i + ACTION_DELTAS[u][0], j + ACTION_DELTAS[u][1]
        idle, imp = view.idleness[a, b], view.importance[a, b]
        total += (p.alpha_T * imp + p.alpha_I) * (min(1.0, idle + p.delta) - p.eta * idle)
    return total


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    nx=st.integers(2, 5),
    ny=st.integers(2, 5),
    n=st.integers(1, 6),
    obstacle_share=st.floats(0.0, 0.3),
)
def test_visit_gain_equals_brute_force_over_its_objective(seed, nx, ny, n, obstacle_share):
    rng, grid, positions, idleness = scene(seed, nx, ny, n, obstacle_share)
    n = len(positions)
    # coarse values so that exact ties occur, as where T = 0 on a real map
    importance = rng.integers(0, 3, grid.shape) / 2.0 * grid.free
    idleness = np.round(idleness * 4) / 4
    view = make_view(grid, positions, idleness, importance)
    policy = VisitGainPolicy()
    policy.reset(grid, n, np.random.default_rng(seed))
    chosen = policy.act(view)

    cells = positions[:, None, :] + ACTION_DELTAS[None]
    best = -np.inf
    for joint in itertools.product(*(np.flatnonzero(f) for f in view.feasible)):
        reached = cells[np.arange(n), joint]
        if len(np.unique(reached[:, 0] * grid.ny + reached[:, 1])) == n:
            best = max(best, visit_gain_objective(view, joint))
    assert view.feasible[np.arange(n), chosen].all()
    # equal up to the tie-breaking jitter (1e-9 relative per drone)
    assert visit_gain_objective(view, chosen) == pytest.approx(best, abs=1e-7)


def test_lookahead_with_horizon_1_is_visit_gain():
    """By construction: with H = 1 the paths are the 5 moves, the predicted idleness of the
    cell reached is ``min(1, I^k + 0 delta) = I^k`` (no earlier step on the path), and the
    cell lies in the field of view, where the importance belief was just set to ``T^k``. So the
    scores are visit-gain's (same expression, :func:`visit_gain`), bit for bit, and with the
    same generator the jitter and hence the actions are the same at every step."""
    _, grid, positions, idleness = scene(3, 9, 11, 6, 0.2)
    look, gain = (
        LookaheadPolicy(horizon=1, end_weight=0.0, plan="independent", beam=0),
        VisitGainPolicy(),
    )
    runs = [
        list(run(policy, np.random.default_rng(5), grid, positions, idleness, steps=40))
        for policy in (look, gain)
    ]
    for (view, a_look), (_, a_gain) in zip(*runs, strict=True):
        np.testing.assert_array_equal(a_look, a_gain)
        feasible = view.feasible
        np.testing.assert_array_equal(look.scores(view)[feasible], gain.scores(view)[feasible])


def test_lookahead_scores_match_a_step_by_step_simulation():
    """Each move's score = best over its feasible paths of the summed visit gains, with the
    idleness map advanced by Def. 3 (one drone) after each step, importance = the belief."""
    rng, grid, positions, idleness = scene(11, 5, 6, 2, 0.2)
    policy = LookaheadPolicy(horizon=3, discount=0.9, end_weight=0.0, plan="independent", beam=0)
    policy.reset(grid, len(positions), np.random.default_rng(0))
    importance = rng.random(grid.shape) * grid.free
    view = make_view(grid, positions, idleness, importance)
    scores = policy.scores(view)
    weight = PARAMS.alpha_T * policy.belief + PARAMS.alpha_I
    for d, start in enumerate(positions):
        expect = np.full(5, -np.inf)
        for seq in itertools.product(range(5), repeat=3):
            idle, pos, value = idleness.copy(), start[None, :], 0.0
            for h, u in enumerate(seq):
                pos = grid.move(pos, [u])
                if not grid.is_free(pos)[0]:
                    break
                i, j = pos[0]
                value += 0.9**h * visit_gain(weight[i, j], idle[i, j], PARAMS)
                idle = update_idleness(idle, pos, grid, PARAMS.eta, PARAMS.delta)
            else:
                expect[seq[0]] = max(expect[seq[0]], value)
        ok = view.feasible[d]
        np.testing.assert_allclose(scores[d][ok], expect[ok], rtol=1e-12)


@pytest.mark.parametrize("horizon, discount", [(1, 1.0), (2, 0.9), (3, 1.0), (4, 0.5)])
def test_lookahead_scores_equal_path_by_path_sums_bit_for_bit(horizon, discount):
    """The tree of prefixes sums each path's gains in path order, so its scores are the
    path-by-path sums exactly (same float operations in the same order), not just close."""
    rng, grid, positions, idleness = scene(7 + horizon, 7, 8, 4, 0.25)
    p = ScoreParams(eta=0.3, delta=0.4)  # large steps: idleness saturates and recovers
    policy = LookaheadPolicy(
        horizon=horizon, discount=discount, end_weight=0.0, plan="independent", beam=0
    )
    policy.reset(grid, len(positions), np.random.default_rng(0))
    view = make_view(grid, positions, idleness, rng.random(grid.shape) * grid.free, params=p)
    scores = policy.scores(view)
    weight = p.alpha_T * policy.belief + p.alpha_I
    offsets, last, first = action_paths(horizon)
    for d, start in enumerate(positions):
        expect = np.full(5, -np.inf)
        for path, steps in enumerate(start + offsets):
            if not grid.is_free(steps).all():
                continue
            value, pre = 0.0, []
            for h, (i, j) in enumerate(steps):
                s = last[path, h]
                if s < 0:
                    pre.append(np.minimum(1.0, idleness[i, j] + h * p.delta))
                else:
                    pre.append(np.minimum(1.0, p.eta * pre[s] + (h - 1 - s) * p.delta))
                value += discount**h * visit_gain(weight[i, j], pre[h], p)
            expect[first[path]] = max(expect[first[path]], value)
        np.testing.assert_array_equal(scores[d], expect)


def test_lookahead_reads_importance_only_where_seen():
    """The belief holds T only on cells some drone's field of view covered."""
    grid = Grid.open(6, 6)
    positions = np.array([[0, 0], [5, 5]])
    policy = LookaheadPolicy(horizon=3)
    policy.reset(grid, 2, np.random.default_rng(0))
    importance = np.ones(grid.shape)
    policy.scores(make_view(grid, positions, grid.free * 1.0, importance))
    assert policy.belief.sum() == 6  # two corner cells with 2 neighbours each
    assert policy.belief[0, 0] == policy.belief[0, 1] == policy.belief[1, 0] == 1


def test_action_paths_first_action_blocks_and_revisits():
    offsets, last, first = action_paths(3)
    assert len(offsets) == 125
    assert (first.reshape(5, 25) == np.arange(5)[:, None]).all()
    stay = np.flatnonzero((offsets == 0).all(axis=(1, 2)))[0]
    assert last[stay].tolist() == [-1, 0, 1]


@pytest.mark.parametrize("name", COORDINATED)
def test_deterministic_given_the_seed(name):
    _, grid, positions, idleness = scene(2, 8, 9, 5, 0.1)

    def actions(seed):
        steps = run(make_policy(name), np.random.default_rng(seed), grid, positions, idleness, 30)
        return np.array([a for _, a in steps])

    np.testing.assert_array_equal(actions(4), actions(4))
    assert not np.array_equal(actions(4), actions(5))


def lookahead_by_simulation(policy, grid, positions, idleness, params):
    """Reference for the end value and sequential planning: every path of every drone walked
    step by step. ``future[h]`` is the idleness before step ``h`` (``h = H``: the visit
    ``end_wait`` steps after the horizon) of cells the path has not visited, lowered by the
    best paths of the drones planned before when sequential."""
    h_max, p = policy.horizon, params
    steps = np.append(np.arange(h_max), h_max + policy.end_wait)
    future = np.minimum(1.0, idleness[None] + steps[:, None, None] * p.delta)
    weight = p.alpha_T * policy.belief + p.alpha_I
    scores = np.full((len(positions), 5), -np.inf)
    for d, start in enumerate(positions):
        best, best_value = None, -np.inf
        for seq in itertools.product(range(5), repeat=h_max):
            cells = start + np.cumsum(ACTION_DELTAS[list(seq)], axis=0)
            if not grid.is_free(cells).all():
                continue
            value, visits = 0.0, {}  # cell -> (step, idleness before) of its last visit
            for h, (i, j) in enumerate(cells):
                if (i, j) in visits:
                    s, pre_s = visits[i, j]
                    pre = min(1.0, p.eta * pre_s + (h - 1 - s) * p.delta)
                else:
                    pre = future[h, i, j]
                value += policy.discount**h * visit_gain(weight[i, j], pre, p)
                visits[i, j] = (h, pre)
            for (i, j), (s, pre_s) in visits.items():
                later = min(1.0, p.eta * pre_s + (steps[-1] - 1 - s) * p.delta)
                change = visit_gain(weight[i, j], later, p) - visit_gain(
                    weight[i, j], future[-1, i, j], p
                )
                value += policy.end_weight * policy.discount**h_max * change
            scores[d, seq[0]] = max(scores[d, seq[0]], value)
            if value > best_value:
                best, best_value = cells, value
        if policy.plan == "sequential" and best is not None:
            for t, (i, j) in enumerate(best):  # claimed: eta I from now on
                was = future[t, i, j]
                future[:, i, j] = np.minimum(
                    1.0, p.eta * was + np.maximum(steps - 1 - t, 0) * p.delta
                )
    return scores


@pytest.mark.parametrize(
    "horizon, discount, end_weight, end_wait, plan",
    [
        (1, 1.0, 0.7, 0, "independent"),
        (2, 0.9, 1.0, 3, "independent"),
        (3, 1.0, 0.9, 5, "independent"),
        (3, 0.8, 0.0, 5, "sequential"),
        (2, 1.0, 0.5, 10, "sequential"),
        (3, 1.0, 0.9, 5, "sequential"),
    ],
)
def test_lookahead_end_value_and_sequential_match_a_simulation(
    horizon, discount, end_weight, end_wait, plan
):
    rng, grid, positions, idleness = scene(20 + horizon, 7, 8, 4, 0.2)
    positions = positions[np.argsort(positions[:, 1])]  # neighbours, so the plans interact
    p = ScoreParams(eta=0.3, delta=0.2)
    policy = LookaheadPolicy(horizon, discount, end_weight, end_wait, plan, beam=0)
    policy.reset(grid, len(positions), np.random.default_rng(0))
    view = make_view(grid, positions, idleness, rng.random(grid.shape) * grid.free, params=p)
    scores = policy.scores(view)
    expect = lookahead_by_simulation(policy, grid, positions, idleness, p)
    ok = view.feasible
    np.testing.assert_allclose(scores[ok], expect[ok], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("horizon, discount", [(1, 1.0), (3, 0.9), (4, 1.0)])
def test_lookahead_without_end_value_keeps_its_scores_bit_for_bit(horizon, discount):
    """``end_weight = 0`` (independent) is the planner without an end value: the same scores
    as the path-by-path sums, whatever ``end_wait``."""
    rng, grid, positions, idleness = scene(3 + horizon, 8, 9, 5, 0.2)
    view = make_view(grid, positions, idleness, rng.random(grid.shape) * grid.free)
    got = []
    for wait in (0, 7):
        policy = LookaheadPolicy(horizon, discount, 0.0, wait, "independent", beam=0)
        policy.reset(grid, len(positions), np.random.default_rng(0))
        got.append(policy.scores(view))
    reference = LookaheadPolicy(horizon, discount, end_weight=0.0, plan="independent", beam=0)
    reference.reset(grid, len(positions), np.random.default_rng(0))
    reference.scores(view)  # sets the importance belief
    expect = lookahead_by_simulation(reference, grid, positions, idleness, PARAMS)
    ok = view.feasible
    for scores in got:
        np.testing.assert_array_equal(scores, got[0])
        np.testing.assert_allclose(scores[ok], expect[ok], rtol=1e-12)


@pytest.mark.parametrize(
    "options",
    [
        {"end_weight": -0.1},
        {"end_weight": 11},
        {"end_wait": -1},
        {"end_wait": 2.5},
        {"plan": "greedy"},
    ],
)
def test_lookahead_rejects_bad_end_options(options):
    with pytest.raises(UserError):
        LookaheadPolicy(horizon=2, **options)


@pytest.mark.parametrize("plan", ["independent", "sequential"])
@pytest.mark.parametrize("horizon, end_weight", [(1, 0.0), (3, 0.9), (4, 0.5)])
def test_lookahead_beam_wide_enough_is_the_full_tree(plan, horizon, end_weight):
    """A beam that keeps every prefix (``5^(H-1)`` per first action) searches all paths."""
    rng, grid, positions, idleness = scene(40 + horizon, 7, 8, 4, 0.2)
    positions = positions[np.argsort(positions[:, 1])]
    p = ScoreParams(eta=0.3, delta=0.2)
    view = make_view(grid, positions, idleness, rng.random(grid.shape) * grid.free, params=p)
    scores = []
    for beam in (0, 5 ** (horizon - 1)):
        policy = LookaheadPolicy(horizon, 1.0, end_weight, 4, plan, beam=beam)
        policy.reset(grid, len(positions), np.random.default_rng(0))
        scores.append(policy.scores(view))
    ok = view.feasible
    np.testing.assert_allclose(scores[1][ok], scores[0][ok], rtol=1e-12, atol=1e-12)


def test_lookahead_beam_reaches_long_horizons():
    _, grid, positions, idleness = scene(5, 12, 14, 4, 0.1)
    policy = LookaheadPolicy(horizon=8, end_weight=0.9, plan="sequential", beam=20)
    actions = [a for _, a in run(policy, np.random.default_rng(1), grid, positions, idleness, 20)]
    assert len(actions) == 20
    with pytest.raises(UserError):
        LookaheadPolicy(horizon=8, beam=0)  # the full tree stops at MAX_HORIZON

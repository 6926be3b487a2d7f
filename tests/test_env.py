"""twin.env: PettingZoo's and Gymnasium's API checks over synthetic, tape and live SUMO traffic,
and the env scoring a policy exactly as the patrol loop does."""

from __future__ import annotations

import re
import warnings
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pettingzoo")
pytest.importorskip("gymnasium")

from gymnasium.utils.env_checker import check_env
from helpers import random_tape, small_sumo_scenario
from pettingzoo.test import parallel_api_test

from twin.env import SwarmGymEnv, SwarmParallelEnv, make_env
from twin.grid import Grid
from twin.patrol import random_starts, run_patrol, swarm_rng, swarm_view
from twin.scores import ScoreParams, drone_states
from twin.swarm import InfeasibleActionError
from twin.swarms import make_policy
from twin.traffic.synthetic import Disturbance, SyntheticTraffic
from twin.traffic.tape import Tape, TapeTraffic

PARAMS = ScoreParams(alpha_T=1.0, alpha_I=0.5)


def _synthetic(horizon: int = 12, grid: Grid | None = None) -> SyntheticTraffic:
    if grid is None:
        obstacles = np.zeros((6, 8), bool)
        obstacles[2, 3:5] = True
        grid = Grid(obstacles)
    disturbances = [Disturbance("big", 1, 2, 1.0, 1.5), Disturbance("small", 4, 6, 0.7, 1.0)]
    return SyntheticTraffic(grid, disturbances, horizon=horizon)


def _tape() -> Tape:
    return random_tape(seed=2, nx=4, ny=5, warmup=2, horizon=6, obstacle=(1, 1))


def _api_test(env) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the test only warns about missing or extra keys
        parallel_api_test(env, num_cycles=100)


def test_parallel_api_on_synthetic_traffic():
    _api_test(SwarmParallelEnv(_synthetic(), n_drones=3, params=PARAMS))


def test_parallel_api_on_a_replayed_tape(tmp_path: Path):
    _tape().write(tmp_path / "tape.parquet")
    env = SwarmParallelEnv(lambda: TapeTraffic.from_file(tmp_path / "tape.parquet"), n_drones=2)
    _api_test(env)
    env.close()


def test_env_scores_the_greedy_swarm_as_run_patrol():
    source, seed, n = _synthetic(horizon=20), 3, 4
    starts = random_starts(source.grid, n, np.random.default_rng(seed))
    patrol = run_patrol(source, {"greedy": make_policy("greedy")}, starts, PARAMS, seed)

    env = SwarmParallelEnv(source, n_drones=n, params=PARAMS)
    obs, _ = env.reset(seed=seed)
    greedy = make_policy("greedy")
    greedy.reset(source.grid, n, swarm_rng(seed, "greedy"))
    rewards, paper, truncated = [], [], {}
    while env.agents:
        s = env.swarm
        states = drone_states(source.grid, s.idleness, s.importance, s.positions)
        for d, agent in enumerate(env.agents):
            np.testing.assert_array_equal(obs[agent]["observation"], states[d].astype(np.float32))
            np.testing.assert_array_equal(obs[agent]["action_mask"], s.feasible[d])
        actions = greedy.act(swarm_view(s, env.horizon, source.grid, PARAMS))
        obs, rew, _, truncated, infos = env.step(dict(zip(env.agents, actions, strict=True)))
        rewards.append(sum(rew.values()))
        paper.append(sum(i["reward_paper"] for i in infos.values()))
    assert all(truncated.values()) and len(rewards) == source.horizon
    np.testing.assert_allclose(rewards, patrol.rewards[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(paper, patrol.reward_paper[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(env.swarm.positions, patrol.positions[0, -1])

    joint = SwarmGymEnv(source, n_drones=n, params=PARAMS)
    _, info = joint.reset(seed=seed)  # the same start cells from the same seed
    greedy.reset(source.grid, n, swarm_rng(seed, "greedy"))
    totals = []
    for _ in range(source.horizon):
        view = swarm_view(joint.swarm_env.swarm, source.horizon, source.grid, PARAMS)
        np.testing.assert_array_equal(info["action_mask"], view.feasible)
        _, r, _, truncated, info = joint.step(greedy.act(view))
        totals.append(r)
    assert truncated
    np.testing.assert_allclose(totals, patrol.rewards[0], rtol=1e-12, atol=1e-12)


def test_gymnasium_checks_pass():
    # check_env steps unmasked random actions, which a drone at the border can't take: with the
    # default (infeasible actions raise) the drones start one cell off every border on an open
    # grid, where all 5 actions are feasible for the one step each check takes.
    source = _synthetic(grid=Grid.open(6, 8))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(SwarmGymEnv(source, starts=[[1, 1], [3, 4], [4, 6]]), skip_render_check=True)
        # infeasible = "stay": random starts, obstacles
        check_env(SwarmGymEnv(_synthetic(), n_drones=3, infeasible="stay"), skip_render_check=True)


def test_infeasible_actions_raise_before_the_source_moves_on():
    env = SwarmParallelEnv(_synthetic(), starts=[[0, 0], [5, 7]])
    env.reset(seed=0)
    with pytest.raises(InfeasibleActionError, match=r"drone 0 at \(0, 0\): action 1 \(up\)"):
        env.step({"drone_0": 1, "drone_1": 0})
    _, rewards, *_ = env.step({"drone_0": 2, "drone_1": 0})  # still at step 0: goes on fine
    assert env.swarm.k == 1 and set(rewards) == {"drone_0", "drone_1"}
    with pytest.raises(ValueError, match="no action for drone_1"):
        env.step({"drone_0": 0})
    with pytest.raises(ValueError, match="two drones on one cell"):
        SwarmParallelEnv(_synthetic(), starts=[[0, 0], [0, 0]])
    # the joint env's error says how to make it take any action of its space (probe 26's u02)
    joint = SwarmGymEnv(_synthetic(), starts=[[0, 0], [5, 7]])
    joint.reset(seed=0)
    with pytest.raises(InfeasibleActionError, match=r"action 1 \(up\) .*infeasible=\"stay\""):
        joint.step([1, 0])


def test_make_env_from_the_shipped_synthetic_config():
    env = make_env("synthetic", joint=True)
    obs, info = env.reset(seed=1)
    assert obs.shape == env.observation_space.shape and info["action_mask"].shape[1] == 5
    env.close()


def test_parallel_api_on_live_sumo(tmp_path: Path):
    pytest.importorskip("libsumo")
    from twin.config import load_config
    from twin.sumo.scenario import sumo_source

    small_sumo_scenario(tmp_path, horizon=3)  # a 5 x 5 grid, 3 steps of 60 s
    config = load_config(tmp_path / "small.toml")
    built = []

    def factory():
        built.append(sumo_source(config))
        return built[-1]

    env = SwarmParallelEnv(factory, n_drones=2)
    _api_test(env)  # three resets: one SUMO run each (libsumo holds one run at a time)
    assert len(built) == 3
    # the first run stopped at T^0 (reset again at once), the others ran the horizon alike
    assert [s.snapshots[-1][0] for s in built] == [0, 3, 3]
    np.testing.assert_array_equal(built[1].snapshots[-1][2], built[2].snapshots[-1][2])
    env.close()


def test_without_the_extra_the_import_names_the_fix():
    import subprocess
    import sys

    code = "import sys; sys.modules['pettingzoo'] = None; import twin.env"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 1
    assert run.stderr.strip().splitlines()[-1] == (
        "ImportError: twin.env needs gymnasium and pettingzoo: pip install 'twin[env]'"
    )


@pytest.mark.parametrize("joint", ["no", "false", 1, None, ""])
def test_make_env_takes_joint_as_a_bool_only(joint):
    """``joint="no"`` built the joint env (any truthy value did; probe 22's f02): a value that
    is not True or False is refused naming it."""
    from twin.env import EnvInputError, make_env

    with pytest.raises(
        EnvInputError, match=rf"make_env\(joint={re.escape(repr(joint))}\): give True"
    ):
        make_env("synthetic", joint=joint)


@pytest.mark.parametrize("joint", [False, True])
def test_make_env_refuses_bad_options_in_one_line(joint):
    from twin.env import EnvInputError

    for options, words in (
        ({"n_drones": 2.5}, "n_drones = 2.5"),
        ({"n_drones": "3"}, "n_drones = '3'"),
        ({"n_drones": 601}, "n_drones = 601"),
        ({"starts": [[0, 0], [1, 1]], "n_drones": 4}, "starts gives 2 cells"),
        ({"starts": [["0", "0"]]}, r"starts must be \(N, 2\) whole-number cells .*not text"),
        ({"starts": np.array([["1", "2"]])}, "not text"),
        ({"starts": [[1e300, 0.0]]}, r"starts\[0\] = \(1e\+300, 0\) is off the"),  # not 301 digits
        ({"starts": [[1234567, 0]]}, r"starts\[0\] = \(1234567, 0\) is off the"),  # as given
        ({"colour": "red"}, r"make_env\(colour=\.\.\.\) is not an option"),
        ({"params": {"eta": 2}}, r"params = \{'eta': 2\} is not a ScoreParams"),
        (
            {"params": ScoreParams(eta=5.0)},
            r"params.eta = 5.0 must be < 1.0; e.g. 0.1 \(the default\)",
        ),
        ({"params": ScoreParams(delta=-1.0)}, r"params.delta = -1.0 must be >= 1e-09"),
        ({"params": ScoreParams(delta=1.0)}, r"params.delta = 1.0 must be < 1"),
        (
            {"params": ScoreParams(alpha_T=float("nan"))},
            r"params.alpha_T = nan must be a finite number",
        ),
        (
            {"params": ScoreParams(alpha_I=float("inf"))},
            r"params.alpha_I = inf must be a finite number",
        ),
        ({"params": ScoreParams(alpha_I=-0.5)}, r"params.alpha_I = -0.5 must be >= 0"),
        ({"params": ScoreParams(alpha_T=1e308)}, r"params.alpha_T = 1e\+308 must be <= 1000000"),
        ({"params": ScoreParams(delta=1e-320)}, r"params.delta = 1e-320 must be >= 1e-09"),
        ({"params": ScoreParams(alpha_T=0.0, alpha_I=0.0)}, "are both 0"),
        ({"params": ScoreParams(alpha_T="1")}, r"params.alpha_T = '1' must be a number"),
        ({"params": ScoreParams(eta=True)}, r"params.eta = True must be a number"),
        ({"params": ScoreParams(alpha_I=np.bool_(True))}, r"params.alpha_I = True must be a"),
        ({"params": ScoreParams(alpha_T=np.bool_(False))}, r"params.alpha_T = False must be a"),
        # a Decimal failed at step(), complex and 0-d arrays passed (probe 19's P2-07)
        (
            {"params": ScoreParams(alpha_I=Decimal("0.5"))},
            r"params.alpha_I = Decimal\('0.5'\) must",
        ),
        ({"params": ScoreParams(alpha_I=np.complex128(0.5))}, r"params.alpha_I = .*must be a num"),
        ({"params": ScoreParams(eta=np.array(0.2))}, r"params.eta = array\(0.2\) must be a num"),
        ({"tape": ""}, r"make_env\(tape=''\): give a tape.parquet's path"),
        ({"tape": 3}, r"make_env\(tape=3\): give a tape.parquet's path"),
        ({"state": ["paper"]}, r"state = \['paper'\] is not a state variant's name"),
        ({"state": {}}, r"state = \{\} is not a state variant's name"),
        ({"state": "bogus"}, r"state = 'bogus' is not a state variant; use one of"),
    ):
        with pytest.raises(EnvInputError, match=words) as info:
            make_env("synthetic", joint=joint, **options)
        assert "\n" not in str(info.value)
    make_env("synthetic", joint=joint, params=ScoreParams(eta=0.2, alpha_I=0.0))  # in range
    make_env("synthetic", joint=joint, params=ScoreParams(eta=np.float32(0.2), alpha_I=np.int64(2)))
    for config in (123, None, ["synthetic"]):
        with pytest.raises(EnvInputError, match="give a scenario config's path"):
            make_env(config, joint=joint)
    for config in ("drone-loss", "coordinator-down"):  # faults were dropped (probe 19's P2-10)
        with pytest.raises(EnvInputError, match=r"\[faults\] scripts lost drones") as info:
            make_env(config, joint=joint)
        assert "\n" not in str(info.value) and f"{config}.toml" in str(info.value)
    if not joint:
        with pytest.raises(EnvInputError, match=r"infeasible=\.\.\.\) is not an option of the"):
            make_env("synthetic", infeasible="stay")
    if joint:
        with pytest.raises(EnvInputError, match=r'infeasible = .maybe.: use "raise" or "stay"'):
            make_env("synthetic", joint=True, infeasible="maybe")


@pytest.mark.parametrize(
    "source, words",
    [
        (42, "source is int, not a traffic source"),
        (lambda: None, r"source\(\) is NoneType, not a traffic source"),
        (lambda: "tape.parquet", r"source\(\) is str, not a traffic source"),
    ],
)
def test_env_refuses_what_is_no_traffic_source_in_one_line(source, words):
    from twin.env import EnvInputError

    with pytest.raises(EnvInputError, match=words) as info:
        SwarmParallelEnv(source, n_drones=2)
    assert "\n" not in str(info.value)


def test_a_factory_that_changes_its_scenario_is_refused_at_reset():
    from twin.env import EnvInputError

    sources = iter([_synthetic(), _synthetic(horizon=5)])
    env = SwarmParallelEnv(lambda: next(sources), n_drones=2)
    env.reset(seed=0)
    with pytest.raises(EnvInputError, match="another grid or horizon"):
        env.reset(seed=1)


@pytest.mark.parametrize("infeasible", ["raise", "stay"])
@pytest.mark.parametrize("action", [[9, 0, 0], [0, -5, 0], [0, 0, 5]])
def test_joint_env_refuses_actions_out_of_range_in_either_mode(infeasible, action):
    """ "stay" replaces a move off the map or into an obstacle, never a number that is no
    action at all."""
    from twin.env import EnvInputError

    env = SwarmGymEnv(_synthetic(), n_drones=3, infeasible=infeasible)
    env.reset(seed=0)
    with pytest.raises(EnvInputError, match=r"is out of range 0 \.\. 4") as info:
        env.step(np.array(action))
    assert "\n" not in str(info.value)
    env.step(np.zeros(3, np.int64))  # the env is still usable


def test_a_tape_that_stopped_early_is_refused_when_the_env_is_made(tmp_path):
    """An env's episode runs every step of its tape's horizon: a tape cut short (a run that
    stopped early) is one EnvInputError line at make_env, not a RuntimeError mid-episode."""
    from helpers import cut_tape, random_tape

    from twin.env import EnvInputError

    full = random_tape(seed=1, nx=6, ny=6, horizon=10)
    short = cut_tape(full, 6)
    short.write(tmp_path / "short.parquet")
    full.write(tmp_path / "full.parquet")
    make_env("synthetic", tape=tmp_path / "full.parquet")
    with pytest.raises(EnvInputError, match=r"short\.parquet: holds steps to 6 of its horizon"):
        make_env("synthetic", tape=tmp_path / "short.parquet")


def test_a_scenario_notice_is_said_once_per_env_not_at_every_episode(capsys):
    """A factory builds the scenario again at every reset (a live SUMO env); its notices
    (the same lines each time) are said once per env (probe 11's s04: two lines per episode)."""
    from twin.notices import notify

    def factory():
        notify("twin: notice: few cells per drone")
        return _synthetic()

    env = SwarmParallelEnv(factory, n_drones=2)
    for seed in range(3):
        env.reset(seed=seed)
    env.close()
    assert capsys.readouterr().err.count("few cells per drone") == 1
    SwarmParallelEnv(factory, n_drones=2).reset(seed=0)  # another env says it again
    assert capsys.readouterr().err.count("few cells per drone") == 1


def test_an_env_past_the_memory_limit_is_refused_before_its_maps(tmp_path):
    """make_env of a grid whose maps do not fit: twin's one line with the estimate, before any
    map is made (it was numpy's MemoryError, or the machine swapping; probe 16's f12)."""
    from twin.env import EnvInputError, make_env

    config = tmp_path / "big.toml"
    config.write_text(
        '[grid]\nnx = 4900\nny = 5000\n[traffic]\nkind = "synthetic"\nhorizon = 2000\n'
        'disturbances = [{ kind = "big", i = 2, j = 2, amplitude = 1.0, sigma = 1.0 }]\n'
    )
    with pytest.raises(EnvInputError, match=r"4900 x 5000 cells x 2000 steps .* need about"):
        make_env(config)


def test_a_live_env_left_open_with_large_maps_lets_its_script_end(tmp_path: Path):
    """A script that makes a live env of large maps and ends without closing it: it ends (its
    SUMO child, blocked sending a map nobody read, ignored multiprocessing's SIGTERM and was
    waited for forever; probe 16's P2-e1)."""
    import subprocess
    import sys

    pytest.importorskip("libsumo")
    small_sumo_scenario(tmp_path, horizon=3)
    text = (tmp_path / "small.toml").read_text().replace("cell_m = 200.0", "cell_m = 2.0")
    text = text.replace("drone_speed_kmh = 12.0", "drone_speed_kmh = 0.12")  # 60 s steps
    (tmp_path / "fine.toml").write_text(text)
    script = (
        "from twin.env import make_env\n"
        "e = make_env('fine.toml')\n"
        "e.reset(seed=0)\n"
        "e.step({a: 0 for a in e.agents})\n"
        "print('stepped', flush=True)\n"
    )
    root = Path(__file__).resolve().parents[1]
    env = {**__import__("os").environ, "PYTHONPATH": str(root)}
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0 and "stepped" in done.stdout, done.stderr


#: How a scenario asks SUMO for outputs: name -> (file, its text, the scenario's key for it,
#: the output it asks for).
ASKED_OUTPUTS = {
    "sumocfg": (
        "outs.sumocfg",
        '<configuration><input><net-file value="small.net.xml"/><route-files '
        'value="small.trips.xml"/></input><output><tripinfo-output value="trip.xml"/></output>'
        "</configuration>",
        'sumocfg = "outs.sumocfg"\n',
        "trip.xml",
    ),
    "additional": (
        "ed.add.xml",
        '<additional><edgeData id="ed" period="60" file="ed.xml"/></additional>',
        'net = "small.net.xml"\nroutes = ["small.trips.xml"]\nadditional = ["ed.add.xml"]\n',
        "ed.xml",
    ),
}


@pytest.mark.parametrize("asked", list(ASKED_OUTPUTS))
def test_a_live_envs_scenario_notices_come_once_over_its_episodes(tmp_path: Path, capfd, asked):
    """A scenario whose sumocfg or additional file asks SUMO for outputs: its "not kept"
    notice once per env, over resets and over episodes stepped to their end (the forked
    simulation's notices came as it ended, outside the env's count; probe 16's f10, probe 17's
    f08)."""
    pytest.importorskip("libsumo")
    from twin.env import make_env

    small_sumo_scenario(tmp_path, horizon=2)
    name, text, key, output = ASKED_OUTPUTS[asked]
    (tmp_path / name).write_text(text)
    config = (tmp_path / "small.toml").read_text()
    config = config.replace('net = "small.net.xml"\nroutes = ["small.trips.xml"]\n', key)
    (tmp_path / "outs.toml").write_text(config)
    env = make_env(tmp_path / "outs.toml")
    for seed in range(2):  # episodes stepped to their end, then ones reset midway
        observations, _ = env.reset(seed=seed)
        while env.agents:
            observations, *_ = env.step(
                {a: int(np.flatnonzero(o["action_mask"])[0]) for a, o in observations.items()}
            )
    for seed in range(3):
        env.reset(seed=seed)
    env.close()
    err = capfd.readouterr().err
    assert err.count("are not kept by this command") == 1, err
    assert not (tmp_path / output).exists()


@pytest.mark.parametrize("kind", ["parallel", "gym"])
def test_render_warns_that_there_is_no_render_mode_and_returns_none(kind):
    """``render()`` raised a bare NotImplementedError (probe 28's z01); without a render mode
    Gymnasium's environments warn and return None."""
    env_type = SwarmParallelEnv if kind == "parallel" else SwarmGymEnv
    env = env_type(_synthetic(), n_drones=2, params=PARAMS)
    env.reset(seed=0)
    assert env.render_mode is None and env.metadata["render_modes"] == []
    with pytest.warns(UserWarning, match="no render mode .*twin run --gui"):
        assert env.render() is None
    env.close()

"""The shenzhen_like generator: plain XML -> netconvert -> a 20 x 30 grid with obstacles."""

from __future__ import annotations

import os

import numpy as np
import pytest

pytest.importorskip("sumolib")

from twin.errors import UserError
from twin.resources import network_spec
from twin.sumo.cells import grid_over, read_lanes
from twin.sumo.network import build_named_network, load_spec, write_plain_xml
from twin.sumo.tools import binary, run_sumo_program


@pytest.fixture(scope="module")
def shenzhen(tmp_path_factory):
    d = tmp_path_factory.mktemp("shenzhen")
    spec = load_spec(network_spec("shenzhen_like"))
    nod, edg = write_plain_xml(spec, d / "sz")
    net = d / "sz.net.xml"
    run_sumo_program(
        [binary("netconvert"), "--node-files", str(nod), "--edge-files", str(edg),
         "-o", str(net), "--offset.disable-normalization", "true",
         "--no-internal-links", "true", "--no-warnings", "true"],
        what="netconvert",
    )  # fmt: skip
    return spec, net


def test_grid_is_20_by_30_with_water_and_hills_as_obstacles(shenzhen):
    _, net = shenzhen
    geometry = grid_over(read_lanes(net), 500.0)
    assert (geometry.nx, geometry.ny) == (20, 30)
    obstacles = geometry.obstacles()
    assert 60 < obstacles.sum() < 200
    # the bay in the south-west, the hills in the north, open city in the middle
    assert obstacles[19, 0] and obstacles[0, 5] and not obstacles[10, 15]
    # the boulevard row carries the most lane-km per cell
    row = np.argmax(np.median(geometry.lane_km, axis=1))
    assert abs(geometry.y_top - (row + 0.5) * 500.0 - 5250.0) < 1.0


def test_boulevard_has_eight_lanes_and_junctions_are_signalised(shenzhen):
    import sumolib

    _, net = shenzhen
    network = sumolib.net.readNet(str(net))
    lanes = {e.getLaneNumber() for e in network.getEdges() if e.getName() == "Shennan Boulevard"}
    assert lanes == {4}  # per direction: 8 lanes
    signals = [n for n in network.getNodes() if n.getType() == "traffic_light"]
    assert len(signals) > 100


def test_unknown_network_name_is_a_user_error():
    with pytest.raises(UserError, match="unknown network 'atlantis'"):
        build_named_network("atlantis")


def test_a_run_outside_the_built_in_networks_demand_is_refused(tmp_path, capsys):
    """The built-in rush hour departs 06:30-10:00: a run at 23:00 was a folder of empty maps
    with a notice after the fact, where a network brought with its own demand is refused
    before SUMO starts (probe 20's f04)."""
    from twin.cli import main

    out = tmp_path / "run"
    code = main(["run", "--begin", "23:00", "--horizon", "4", "--swarms", "random",
                 "--no-ceiling", "--no-report", "--quiet", "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "shenzhen_like: the run (23:00:00 - 23:05:00) lies outside the demand" in err, err
    assert not out.exists()


def test_a_stop_asked_while_a_sumo_tool_runs_stops_it_and_its_children(tmp_path):
    """A first Ctrl-C (or SIGTERM) while randomTrips builds the demand: the tool and what it
    started (duarouter) are stopped at once and the command is interrupted (exit 130), not
    run on for minutes nor blamed on the network (probe 23's P2-f03, P2-f04)."""
    import os
    import threading
    import time

    from twin.processes import STOP_ASKED
    from twin.sumo.tools import run_sumo_program

    pid_file = tmp_path / "child.pid"
    tool = tmp_path / "slow.py"
    tool.write_text(
        "import subprocess, sys, time\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        f"open({str(pid_file)!r}, 'w').write(str(child.pid))\n"
        "time.sleep(60)\n"
    )
    timer = threading.Timer(1.0, STOP_ASKED.set)
    timer.start()
    start = time.monotonic()
    try:
        with pytest.raises(KeyboardInterrupt):
            run_sumo_program([str(tool)], what="slow.py")
    finally:
        timer.cancel()
        STOP_ASKED.clear()
    assert time.monotonic() - start < 10
    child = int(pid_file.read_text())
    for _ in range(50):  # killed with its group; reaped by init
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail(f"the tool's child {child} outlived the stop")


class _FakeSource:
    """What :func:`twin.sumo.worker.maps_from_child` asks of a live source, doing nothing."""

    detectors, detector_readings = [], []
    error, model, output_dir, read_seconds = None, None, None, 0.0
    separate_process, defer_close, _truth, _incidents = True, False, None, None

    def truth_map(self):
        return None

    def incidents_info(self):
        return []

    def close_deferred(self):
        pass


def test_a_second_ctrl_c_stops_the_sumo_child_at_once(tmp_path):
    """Ctrl-C again while SUMO's own process is deep in a long advance (a warm-up of a big
    demand): the child is killed at once, not waited for to send its end state (30-40 s:
    probe 23's P2-f04)."""
    import signal
    import threading
    import time
    from types import SimpleNamespace

    from twin.sumo.worker import maps_from_child

    class Slow(_FakeSource):  # a source whose first map takes a minute
        snapshots, vehicles_seen = [], []
        scenario = SimpleNamespace(name="slow")

        def maps_here(self, warmup_too=False):
            time.sleep(60)
            yield np.zeros((2, 2))

    main = threading.main_thread().ident  # Ctrl-C reaches the main thread, in its recv()
    timer = threading.Timer(1.5, signal.pthread_kill, (main, signal.SIGINT))
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (a
    timer.start()  # test worker may ignore it)
    start = time.monotonic()
    try:
        with pytest.raises(KeyboardInterrupt):
            next(maps_from_child(Slow()))
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, before)
    assert time.monotonic() - start < 10


class _Crashing(_FakeSource):
    """A source whose SUMO process crashes (SIGSEGV) after ``maps`` maps."""

    def __init__(self, maps: int):
        from types import SimpleNamespace

        self.maps, self.snapshots, self.vehicles_seen = maps, [], []
        self.scenario = SimpleNamespace(name="crashing")

    def maps_here(self, warmup_too=False):
        import signal

        for k in range(self.maps):
            self.snapshots.append((k, k * 60.0, np.ones((2, 2)), np.ones((2, 2))))
            self.vehicles_seen.append(4)
            yield np.zeros((2, 2))
        import faulthandler

        faulthandler.disable()  # (pytest's dump of the crash is no news here)
        os.write(2, b"Error: no lane here\n")  # SUMO's last words, on its stderr
        os.kill(os.getpid(), signal.SIGSEGV)

    def model_after(self, snapshots):
        return ("model after", len(snapshots))


class _WarmingUp(_FakeSource):
    """A source with a warm-up of 5 snapshots before 3 maps; each map holds the number of
    snapshots its process held when it was read."""

    def __init__(self):
        from types import SimpleNamespace

        self.snapshots, self.vehicles_seen = [], []
        self.scenario = SimpleNamespace(name="warming up")

    def maps_here(self, warmup_too=False):
        for k in range(-5, 3):
            held = len(self.snapshots)
            self.snapshots.append((k, k * 60.0, np.ones((2, 2)), np.ones((2, 2))))
            self.vehicles_seen.append(4)
            if k >= 0:
                yield np.full((2, 2), float(held))
            elif warmup_too:
                yield None


def test_sumo_child_sends_each_snapshot_on_and_holds_none_it_sent():
    """A long warm-up (1 s steps: 900 snapshots of the grid) was held in SUMO's process and sent
    with the first map in one message: three copies of it at once (probe 28's n01)."""
    from twin.sumo.worker import maps_from_child

    source = _WarmingUp()
    maps = list(maps_from_child(source))
    assert [int(m[0, 0]) for m in maps] == [0, 0, 0]  # the child held none it had sent
    assert [s[0] for s in source.snapshots] == list(range(-5, 3))  # the parent has them all
    assert source.vehicles_seen == [4] * 8
    # SUMO's process measures its own peak: the largest child of a parallel run's parent is
    # a worker (probe 31's w01)
    assert source.process_peak_mb is not None and source.process_peak_mb > 0


def test_a_stop_asked_during_the_warm_up_stops_at_once():
    """SIGTERM (a batch scheduler's stop) during a long warm-up waited for the whole warm-up and
    a step, past the scheduler's grace period (probe 30's r03): before the first step there is
    nothing to keep."""
    import time

    from twin.processes import STOP_ASKED
    from twin.sumo.worker import maps_from_child

    class LongWarmUp(_WarmingUp):
        def maps_here(self, warmup_too=False):
            for k in range(-3000, 1):
                time.sleep(0.01)  # 30 s of warm-up
                self.snapshots.append((k, k * 1.0, np.ones((2, 2)), np.ones((2, 2))))
                self.vehicles_seen.append(4)
                if k >= 0:
                    yield np.zeros((2, 2))
                elif warmup_too:
                    yield None

    start = time.monotonic()
    STOP_ASKED.set()
    try:
        with pytest.raises(KeyboardInterrupt):
            next(maps_from_child(LongWarmUp()))
    finally:
        STOP_ASKED.clear()
    assert time.monotonic() - start < 10


def test_sumo_crashing_before_the_first_step_is_an_error_naming_the_signal():
    """SUMO's process dying by a signal before any step: one line naming the signal, not a
    partial run of 0 steps (probe 24's f03)."""
    from twin.errors import UserError
    from twin.sumo.worker import maps_from_child

    with pytest.raises(UserError) as caught:
        list(maps_from_child(_Crashing(0)))
    assert str(caught.value) == (
        "SUMO crashed (SIGSEGV, Segmentation fault) before the first step of scenario "
        "crashing (its last error: no lane here); run SUMO alone on the same files to see "
        "where it fails"
    )


def test_sumo_crashing_mid_run_names_the_signal_and_keeps_the_mfd_of_its_maps():
    """A crash after steps: a partial run whose error names the signal, and whose MFD model
    holds the snapshots it got (it was the empty prior, and the saved samples disagreed with
    the tape: the run ended on a refusal of its own folder)."""
    from twin.sumo.worker import maps_from_child

    source = _Crashing(3)
    got = []
    with pytest.raises(RuntimeError, match=r"SUMO crashed \(SIGSEGV, Segmentation fault\)"):
        for importance in maps_from_child(source):
            got.append(importance)
    assert len(got) == 3
    assert source.model == ("model after", 3)
    assert source.error.startswith("SUMO crashed (SIGSEGV")


def test_how_sumo_ended_is_said_for_each_kind_of_end():
    import signal

    from twin.sumo.worker import how_it_ended

    assert "by the system when memory ran out" in how_it_ended(-signal.SIGKILL)
    assert how_it_ended(-signal.SIGABRT).startswith("crashed (SIGABRT")
    assert how_it_ended(3) == "ended unexpectedly (exit code 3)"
    assert how_it_ended(-200) == "crashed (signal 200)"

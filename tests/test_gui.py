"""``--gui``: sumo-gui under Xvfb draws the drones where they are, changes no result, records.

Needs Xvfb (``apt-get install xvfb``, as ``.ci/run`` does) or a display; skipped otherwise.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import needs_display, small_sumo_scenario
from twin.errors import UserError

HORIZON = 3


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return small_sumo_scenario(tmp_path_factory.mktemp("gui"), horizon=HORIZON)


def _experiment(scenario):
    from twin.config import load_config
    from twin.experiment import Experiment

    return Experiment(
        config=load_config(scenario / "small.toml"),
        swarms=["random", "greedy", "sweeping"],
        seeds=[0],
    )


@pytest.fixture(scope="module")
def gui_run(scenario, tmp_path_factory):
    """The small run under sumo-gui (random and greedy shown) with every frame kept, and the
    header's POI types (clock, legend) as sumo-gui has them at every step."""
    from twin.experiment import run_experiment
    from twin.sumo.gui import GuiDrawer, GuiSettings, display

    frames = tmp_path_factory.mktemp("frames")
    drawer = GuiDrawer(
        GuiSettings(swarms=["random", "greedy"], frames_dir=frames),
        ["random", "greedy", "sweeping"],
    )
    header: list[dict[str, str]] = []

    def on_step(k, positions, importance):
        import traci

        drawer(k, positions, importance)
        pois = traci.poi.getIDList()
        header.append({p: traci.poi.getType(p) for p in pois if p.startswith("legend")})

    with display():
        outcome = run_experiment(
            _experiment(scenario), keep_sources=True, on_source=drawer.attach, on_step=on_step
        )
    return outcome, drawer, header


def _pixel(drawer, x: float, y: float, shape) -> tuple[int, int]:
    (xmin, ymin), (xmax, ymax) = drawer.view_boundary
    h, w = shape[:2]
    return int((ymax - y) / (ymax - ymin) * h), int((x - xmin) / (xmax - xmin) * w)


def _near(image, row, col, colour, radius=6, tol=40) -> int:
    patch = image[max(row - radius, 0) : row + radius + 1, max(col - radius, 0) : col + radius + 1]
    return int((np.abs(patch[..., :3].astype(int) - colour[:3]).max(axis=-1) <= tol).sum())


@needs_display
def test_screenshots_show_the_shown_swarms_drones_where_they_are(gui_run):
    from PIL import Image

    outcome, drawer, _ = gui_run
    result = outcome.results[0]
    geometry = outcome.sources[0].geometry
    assert len(drawer.frames) == HORIZON + 1
    shown = [s for s, name in enumerate(result.swarms) if name in drawer.shown]
    hidden = drawer.colours["sweeping"]  # not in --gui-swarms: its colour is nowhere
    for k in (0, HORIZON):
        image = np.asarray(Image.open(drawer.frames[k]).convert("RGB"))
        assert not (np.abs(image.astype(int) - hidden[:3]).max(axis=-1) <= 40).any()
        for s in shown:
            for i, j in result.positions[s, k]:
                row, col = _pixel(drawer, *geometry.cell_center(i, j), image.shape)
                # swarms on one cell overlap: one of their colours is on top
                there = [
                    result.swarms[t]
                    for t in shown
                    if ((result.positions[t, k] == (i, j)).all(axis=1)).any()
                ]
                found = max(_near(image, row, col, drawer.colours[n]) for n in there)
                assert found > 20, (k, result.swarms[s], i, j)
        assert (image == 255).all(axis=-1).any()  # the frame is not one colour


@needs_display
def test_cells_are_shaded(gui_run):
    from PIL import Image

    outcome, drawer, _ = gui_run
    image = np.asarray(Image.open(drawer.frames[-1]).convert("RGB")).astype(int)
    geometry, grid = outcome.sources[0].geometry, outcome.sources[0].grid
    top, left = _pixel(drawer, geometry.x0, geometry.y_top, image.shape)
    # outside the grid the background is white; inside, the cell fills tint it yellow/red
    bottom, right = _pixel(
        drawer, geometry.x0 + grid.ny * geometry.cell_m, geometry.y_top - grid.nx * geometry.cell_m,
        image.shape,
    )  # fmt: skip
    inside = image[max(top, 0) + 2 : bottom - 2, left + 2 : right - 2]
    assert (inside[..., 2] < 240).mean() > 0.5  # blue channel lowered by the fill
    if left > 5:
        assert (image[:, : left - 3, :3] == 255).all(axis=-1).mean() > 0.9


@needs_display
def test_roads_are_coloured_by_speed_and_vehicles_drawn(gui_run):
    """sumo-gui took twin's view settings: free-flowing roads grey, slow ones orange to red (the
    small grid's signals queue traffic), vehicles dark (not the default black roads)."""
    from PIL import Image

    from twin.sumo.gui import ROAD_SPEED_COLOURS

    drawer = gui_run[1]
    image = np.asarray(Image.open(drawer.frames[-1]).convert("RGB")).astype(int)
    free = tuple(int(v) for v in ROAD_SPEED_COLOURS[-1][1].split(","))
    assert (np.abs(image - free).max(axis=-1) <= 6).sum() > 100
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    assert ((r > 140) & (g < 120) & (b < 60)).sum() > 20  # slow or stopped lanes
    assert (np.abs(image - 30).max(axis=-1) <= 6).sum() > 20  # vehicles


@needs_display
def test_the_header_shows_the_clock_and_the_legend(gui_run):
    """Above the grid: the simulated time and step, a square and the name of each shown swarm
    (POIs whose type sumo-gui writes, so in the live window and in the frames alike)."""
    from PIL import Image

    outcome, drawer, header = gui_run
    clocks = [f"00:0{5 + k}:00  step {k}/{HORIZON}" for k in range(HORIZON + 1)]  # 60 s steps
    assert [h["legend_clock"] for h in header] == clocks
    names = {h: t for h, t in header[-1].items() if h.startswith("legend_name_")}
    assert names == {"legend_name_random": "random", "legend_name_greedy": "greedy"}
    assert any("cells: importance random believes" in t for t in header[-1].values())
    geometry = outcome.sources[0].geometry
    image = np.asarray(Image.open(drawer.frames[-1]).convert("RGB")).astype(int)
    top, _ = _pixel(drawer, geometry.x0, geometry.y_top, image.shape)
    above = image[: top - 2]
    for name in drawer.shown:  # the legend's squares
        assert (np.abs(above - drawer.colours[name][:3]).max(axis=-1) <= 20).sum() > 20, name
    assert (above.max(axis=-1) < 80).sum() > 200  # dark text


@needs_display
def test_gui_results_equal_libsumo_results(gui_run, scenario):
    from twin.experiment import run_experiment

    gui = gui_run[0].results[0]
    plain = run_experiment(_experiment(scenario)).results[0]
    assert gui.completed_steps == plain.completed_steps == HORIZON
    np.testing.assert_array_equal(gui.positions, plain.positions)
    np.testing.assert_array_equal(gui.rewards, plain.rewards)
    np.testing.assert_array_equal(gui.importance, plain.importance)


@needs_display
def test_record_and_replay_write_videos_of_every_step(scenario, tmp_path, monkeypatch):
    pytest.importorskip("imageio_ffmpeg")
    iio = pytest.importorskip("imageio.v3")
    from twin.cli import main

    monkeypatch.chdir(scenario)
    out, video = tmp_path / "run", tmp_path / "run.mp4"
    gif = tmp_path / "videos" / "new" / "replay.gif"  # folders --record creates
    args = ["--config", "small.toml", "--swarms", "random,greedy", "--no-report", "--quiet"]
    assert main(["run", *args, "--out", str(out), "--record", str(video)]) == 0
    assert iio.imread(video).shape[0] == HORIZON + 1
    assert main(["replay", str(out), "--record", str(gif), "--gui-shade", "truth"]) == 0
    assert iio.imread(gif, index=None).shape[0] == HORIZON + 1


@needs_display
def test_sumo_gui_keeps_its_settings_in_the_cache_not_in_home(scenario, tmp_path, monkeypatch):
    """sumo-gui saves its registry (window, recent files) on closing: into twin's cache, the
    user's home (``HOME``, ``XDG_CONFIG_HOME``) untouched."""
    from twin.cli import main
    from twin.resources import cache_dir

    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home / ".config"))
    monkeypatch.chdir(scenario)
    args = ["--config", "small.toml", "--swarms", "random", "--no-report", "--quiet", "--gui"]
    assert main(["run", *args, "--out", str(tmp_path / "run")]) == 0
    assert list(home.iterdir()) == []
    assert (os.environ["HOME"], os.environ["XDG_CONFIG_HOME"]) == (str(home), str(home / ".config"))
    saved = {p.name for p in (cache_dir() / "sumo-gui").rglob("*") if p.is_file()}
    assert saved - {"twin-gui-settings.xml"}, saved  # sumo-gui's own, e.g. .foxrc/sumo-gui/...


def test_no_display_and_no_xvfb_is_one_line_naming_the_fix(monkeypatch, tmp_path):
    from twin.sumo.gui import display

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    with (
        pytest.raises(UserError, match=r"--gui: .*apt-get install xvfb.*DISPLAY") as info,
        display(),
    ):
        pass
    assert "\n" not in str(info.value)


def test_a_display_that_does_not_answer_is_one_line_at_once(monkeypatch):
    """DISPLAY names an X server that is gone (after an ssh -X session): one line naming the
    fix before sumo-gui starts (it retried for a minute, 180 lines: probe 12's gu1)."""
    from twin.sumo.gui import display, display_answers

    free = next(n for n in range(77, 200) if not Path(f"/tmp/.X11-unix/X{n}").exists())
    monkeypatch.setenv("DISPLAY", f":{free}")
    assert not display_answers(f":{free}") and not display_answers("no display")
    words = rf"--gui: the display DISPLAY=:{free} does not answer"
    with pytest.raises(UserError, match=words), display():
        pass


def test_bad_record_name_is_refused_before_the_run():
    from twin.sumo.gui import GuiSettings, check_settings

    with pytest.raises(UserError, match="--record"):
        check_settings(GuiSettings(record=Path("x.avi")), ["greedy"])
    with pytest.raises(UserError, match="--gui-swarms"):
        check_settings(GuiSettings(swarms=["nope"]), ["greedy"])


def test_default_swarms_are_the_learned_and_the_best_classical_one():
    from twin.sumo.gui import default_swarms

    shenzhen = ["random", "greedy", "sweeping", "greedy-coordinated", "visit-gain", "lookahead",
                "tours", "rl", "rl-decentralized"]  # fmt: skip
    assert default_swarms(shenzhen) == ["lookahead", "rl"]
    assert default_swarms(["greedy", "tours", "visit-gain", "rl-decentralized"]) == [
        "tours",
        "rl-decentralized",
    ]
    assert default_swarms(["random", "greedy"]) == ["random"]
    assert default_swarms(["rl-online"]) == ["rl-online"]


def test_gui_swarms_all_shows_every_swarm_and_shown_swarms_take_the_first_colours():
    import argparse

    from twin.cli.run import gui_drawer
    from twin.sumo.gui import SWARM_COLOURS

    args = argparse.Namespace(gui=True, record=None, gui_swarms="all", gui_shade="belief")
    assert gui_drawer(args, ["random", "greedy", "rl"]).shown == ["random", "greedy", "rl"]
    args.gui_swarms = None
    drawer = gui_drawer(args, ["random", "lookahead", "rl"])
    assert drawer.shown == ["lookahead", "rl"]
    assert [drawer.colours[n] for n in drawer.shown] == SWARM_COLOURS[:2]


def test_gui_swarms_without_the_gui_says_it_draws_nothing(capsys):
    """--gui-swarms without --gui or --record is checked and draws nothing: a notice says so
    (it was silently ignored; probe 17's c57)."""
    import argparse

    from twin.cli.run import gui_drawer

    args = argparse.Namespace(gui=False, record=None, gui_swarms="rl", gui_shade="belief")
    assert gui_drawer(args, ["random", "rl"]) is None
    assert "--gui-swarms rl: draws nothing without --gui or --record" in capsys.readouterr().err
    args.gui = True
    gui_drawer(args, ["random", "rl"])
    assert "draws nothing" not in capsys.readouterr().err
    # --gui-shade alike (the review of probe 26); its default is belief
    args = argparse.Namespace(gui=False, record=None, gui_swarms=None, gui_shade="truth")
    assert gui_drawer(args, ["random", "rl"]) is None
    assert "--gui-shade truth: draws nothing without --gui or --record" in capsys.readouterr().err
    args = argparse.Namespace(gui=True, record=None, gui_swarms=None, gui_shade=None)
    assert gui_drawer(args, ["random", "rl"]).settings.shade == "belief"


def test_meso_roads_are_drawn_in_one_colour():
    """sumo-gui's mesoscopic speed colouring changes the simulation it draws: a --meso view
    colours its edges by no scheme that reads the simulation (probe 16's f17)."""
    from twin.sumo.gui import view_settings

    meso = view_settings(mesoscopic=True)
    assert 'laneEdgeMode="0"' in meso and 'colorScheme name="uniform"' in meso
    assert "meso:" not in meso and "threshold" not in meso.split("<vehicles")[0]
    assert "by average relative speed" in view_settings(mesoscopic=False)


@pytest.mark.slow
@needs_display
def test_a_meso_run_replays_again_and_again(tmp_path, capsys):
    """A --meso run of two dense flows, replayed five times: every replay is the recorded run
    (two of six replays drew another run, which the replay refused; probe 16's f17)."""
    import subprocess
    import sys

    from twin.cli import main

    subprocess.run([str(Path(sys.executable).parent / "netgenerate"), "--grid", "--grid.number",
                    "5", "--grid.length", "200", "--default.lanenumber", "2", "-o",
                    str(tmp_path / "grid.net.xml")], check=True, capture_output=True)  # fmt: skip
    (tmp_path / "f.rou.xml").write_text(
        '<routes><vType id="car" vClass="passenger"/>'
        '<flow id="w" type="car" begin="0" end="3000" vehsPerHour="1200" from="A2B2" '
        'to="D2E2" departLane="best"/><flow id="b" type="car" begin="0" end="3000" '
        'vehsPerHour="300" from="A0A1" to="E4E3"/></routes>'
    )
    out = tmp_path / "R"
    assert main(["run", "--net", str(tmp_path / "grid.net.xml"), "--routes",
                 str(tmp_path / "f.rou.xml"), "--cell-m", "100", "--drones", "2", "--seeds", "1",
                 "--swarms", "random", "--no-ceiling", "--quiet", "--no-report", "--meso",
                 "--horizon", "40", "--begin", "00:15", "--out", str(out)]) == 0  # fmt: skip
    for _ in range(5):
        capsys.readouterr()
        assert main(["replay", str(out)]) == 0, capsys.readouterr().err


@pytest.mark.slow
@needs_display
def test_a_meso_run_whose_vehicles_stand_on_cell_borders_replays_and_runs_alike_in_the_gui(
    tmp_path, capsys
):
    """Mesoscopic vehicles stand at segment ends, on the cell borders of a 250 m grid with
    250 m cells; sumo-gui places them 1e-14 m off libsumo: the replay was refused and `--gui`
    wrote another tape (probe 32's a01)."""
    import subprocess
    import sys

    from twin.cli import main

    bin_dir = Path(sys.executable).parent
    subprocess.run([str(bin_dir / "netgenerate"), "--grid", "--grid.number", "5",
                    "--grid.length", "250", "--default.lanenumber", "1", "-o",
                    str(tmp_path / "g.net.xml")], check=True, capture_output=True)  # fmt: skip
    import sumo

    tools = Path(sumo.__file__).parent / "tools"
    # (randomTrips writes a routes.rou.xml where it runs: in tmp_path)
    subprocess.run([sys.executable, str(tools / "randomTrips.py"), "-n",
                    str(tmp_path / "g.net.xml"), "-e", "1800", "-p", "3", "--validate", "--seed",
                    "1", "-o", str(tmp_path / "r.rou.xml")], check=True, capture_output=True,
                   cwd=tmp_path)  # fmt: skip
    argv = ["run", "--net", str(tmp_path / "g.net.xml"), "--routes", str(tmp_path / "r.rou.xml"),
            "--meso", "--cell-m", "250", "--horizon", "6", "--swarms", "random", "--no-ceiling",
            "--quiet", "--no-report"]  # fmt: skip
    assert main([*argv, "--out", str(tmp_path / "m")]) == 0
    assert main(["replay", str(tmp_path / "m")]) == 0, capsys.readouterr().err
    assert main([*argv, "--gui", "--out", str(tmp_path / "g")]) == 0
    tapes = [(tmp_path / f / "tape.parquet").read_bytes() for f in ("m", "g")]
    assert tapes[0] == tapes[1]


@pytest.mark.parametrize("encoder", ["/bin/false", "/bin/true"])
def test_a_failing_video_encoder_is_named_with_a_fix(tmp_path, monkeypatch, encoder):
    """An ffmpeg that fails (or writes nothing): one line naming the encoder and the fixes, no
    video file (it said "[Errno None] None: 'x.mp4'; check the file and the folder"; probe
    17's P2-09)."""
    pytest.importorskip("imageio_ffmpeg")
    from PIL import Image

    from twin.sumo.gui import write_video

    frames = []
    for n in range(3):
        frames.append(tmp_path / f"f{n}.png")
        Image.new("RGB", (32, 24), (n * 40, 0, 0)).save(frames[-1])
    monkeypatch.setenv("IMAGEIO_FFMPEG_EXE", encoder)
    with pytest.raises(UserError, match=rf"--record .*x\.mp4: the video encoder \({encoder}\) "
                                        r"(failed|wrote nothing).*--record FILE\.gif") as info:  # fmt: skip
        write_video(tmp_path / "x.mp4", frames)
    assert "\n" not in str(info.value) and "FFMPEG COMMAND" not in str(info.value)
    assert not (tmp_path / "x.mp4").exists()


@needs_display
def test_a_scenario_with_gui_options_that_stop_a_run_runs_under_the_gui(scenario, tmp_path):
    """A sumocfg's ``<num-clients value="2"/>`` kept sumo-gui waiting for a second client
    forever (probe 19's f08); its ``<breakpoints>`` ended the run at the first, and ``<demo>``
    kept sumo-gui from starting (f09): twin is its one client, and these are off."""
    import subprocess
    import sys

    cfg = tmp_path / "clients.sumocfg"
    cfg.write_text(
        f'<configuration><input><net-file value="{scenario / "small.net.xml"}"/>'
        f'<route-files value="{scenario / "small.trips.xml"}"/></input>'
        '<num-clients value="2"/><gui_only><breakpoints value="400,500"/><demo value="true"/>'
        '<game value="true"/></gui_only></configuration>'
    )
    argv = ["run", "--sumocfg", str(cfg), "--cell-m", "200", "--horizon", "2", "--swarms",
            "random", "--no-ceiling", "--no-report", "--quiet", "--gui", "--out",
            str(tmp_path / "run")]  # fmt: skip
    done = subprocess.run(
        [sys.executable, "-m", "twin", *argv], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr


@needs_display
@pytest.mark.parametrize(
    ("option", "words"),
    [
        ('<alternative-net-file value="nope.net.xml"/>', "Cannot read file '"),  # its log
        ('<osg-view value="true"/>', "osg-view"),  # its stderr: an option this build lacks
    ],
)
def test_sumo_gui_refusing_a_scenario_is_one_line_with_its_reason(scenario, tmp_path, option,
                                                                  words):  # fmt: skip
    """sumo-gui's own refusal was lost ("did not start (Connection closed by SUMO.)", or a
    minute of restarts on other ports): its reason and the file, as libsumo's (probe 19's
    P2-03)."""
    import subprocess
    import sys

    cfg = tmp_path / "refused.sumocfg"
    cfg.write_text(
        f'<configuration><input><net-file value="{scenario / "small.net.xml"}"/>'
        f'<route-files value="{scenario / "small.trips.xml"}"/></input>'
        f"<gui_only>{option}</gui_only></configuration>"
    )
    argv = ["run", "--sumocfg", str(cfg), "--cell-m", "200", "--horizon", "2", "--swarms",
            "random", "--no-ceiling", "--no-report", "--quiet", "--gui", "--out",
            str(tmp_path / "run")]  # fmt: skip
    done = subprocess.run(
        [sys.executable, "-m", "twin", *argv], capture_output=True, text=True, timeout=50
    )
    said = [line for line in done.stderr.splitlines() if not line.startswith("twin: notice:")]
    assert done.returncode == 2 and len(said) == 1, done.stderr  # sumo-gui's own lines held
    assert "sumo-gui refuses it: " in said[0] and words in said[0], said
    assert not (tmp_path / "run").exists()


def test_replays_gui_flag_says_it_is_always_on(capsys):
    """``twin replay --help`` listed --gui as a choice, which changed nothing: a replay is
    always drawn (probe 26b's v03)."""
    from twin.cli import main

    with pytest.raises(SystemExit):
        main(["replay", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--gui (always on: a replay is drawn in sumo-gui" in text


def test_an_active_incident_is_drawn_at_its_cell(monkeypatch):
    """The incidents' records give their ``cell``: the drawer looked for ``i`` and ``j``, so no
    incident was ever drawn (the guide promises them red; probe 27e's m03). Drawn at its
    cell's centre on the steps monitoring counts it, removed after; one off the grid is not
    drawn."""
    from types import SimpleNamespace

    from twin.sumo.gui import GuiDrawer, GuiSettings

    added, removed = {}, []
    fake = SimpleNamespace(
        poi=SimpleNamespace(add=lambda key, x, y, *a, **k: added.update({key: (x, y)}),
                            remove=removed.append),
    )  # fmt: skip
    drawer = GuiDrawer(GuiSettings(), ["random"])
    monkeypatch.setattr(drawer, "_traci", lambda: fake)
    records = [{"cell": [1, 2], "applied_s": 10.0, "onset_step": 2, "end_step": 3},
               {"cell": [-1, -1], "applied_s": 10.0, "onset_step": 2, "end_step": 9}]  # fmt: skip
    geometry = SimpleNamespace(cell_m=200.0, cell_center=lambda i, j: (j * 200.0, -i * 200.0))
    drawer.source = SimpleNamespace(incidents_info=lambda: records, geometry=geometry)
    drawer._incidents = set()  # (as its setup in sumo-gui leaves it)
    drawer._mark_incidents(1)
    assert added == {}  # before the steps monitoring counts it
    for k in (2, 3):
        drawer._mark_incidents(k)
        assert added == {"incident_0": (400.0, -200.0)} and removed == []
    drawer._mark_incidents(4)
    assert removed == ["incident_0"]

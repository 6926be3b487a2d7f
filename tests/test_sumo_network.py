"""The shenzhen_like generator: plain XML -> netconvert -> a 20 x 30 grid with obstacles."""

from __future__ import annotations

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

"""Shipped files found through the package, the user cache, and folders built once."""

from __future__ import annotations

import tomllib
from fnmatch import fnmatch
from pathlib import Path

import pytest

from twin import resources
from twin.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_names_resolve_from_an_empty_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for given in ("synthetic", "synthetic.toml", "configs/synthetic.toml"):
        path = resources.shipped_config(given)
        assert path == resources.shipped("configs", "synthetic.toml") and path.is_file()
    assert "shenzhen" in resources.shipped_config_names()


def test_a_users_file_wins_over_a_shipped_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "configs").mkdir()
    for given in ("synthetic", "synthetic.toml", "configs/synthetic.toml"):
        Path(given).write_text("# mine\n")
        assert resources.shipped_config(given) == Path(given)


def test_unknown_config_is_one_line_naming_the_shipped_ones(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for given in ("atlantis", "elsewhere/synthetic.toml"):
        with pytest.raises(UserError, match=r"config file not found; .*synthetic") as err:
            resources.shipped_config(given)
        assert str(err.value).startswith(given) and "\n" not in str(err.value)


def test_network_specs_and_checkpoint_are_shipped():
    assert "shenzhen_like" in resources.network_names()
    assert tomllib.loads(resources.network_spec("shenzhen_like").read_text())["lattice"]
    assert resources.shipped_checkpoint().is_file()
    with pytest.raises(UserError, match=r"unknown network 'atlantis'.*shenzhen_like"):
        resources.network_spec("atlantis")


ROOT_NAME = Path(__file__).resolve().parents[1].name


@pytest.mark.parametrize(
    "name",
    [f"../../{ROOT_NAME}/networks/shenzhen_like", "shenzhen_like/../shenzhen_like", "/x/y"],
)
def test_a_network_name_is_no_path(tmp_path, monkeypatch, name):
    """A built-in network is named, never reached by a path: `twin network build NAME` with
    '..' in NAME made folders beside the cache, then failed with an internal error."""
    from twin.cli import main

    cache = tmp_path / "a" / "cache"
    monkeypatch.setenv("TWIN_CACHE_DIR", str(cache))
    assert main(["network", "build", name]) == 2
    assert sorted(p.name for p in tmp_path.rglob("*")) <= ["a", "cache"], list(tmp_path.rglob("*"))


def test_every_shipped_file_is_package_data_of_the_wheel():
    """What resources hands out lies under twin/ and matches pyproject's package-data globs,
    so a wheel (non-editable install) carries it."""
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["twin"]
    root = resources.package_root()
    files = [
        *(resources.shipped_config(n) for n in resources.shipped_config_names()),
        *(resources.network_spec(n) for n in resources.network_names()),
        resources.shipped_checkpoint(),
    ]
    for path in files:
        rel = path.relative_to(root).as_posix()
        assert any(fnmatch(rel, g) for g in globs), rel
    # the repository keeps its top-level folders; twin/ links to them
    for name in ("configs", "networks", "data"):
        assert (root / name).resolve() == (ROOT / name).resolve()


def test_cache_dir_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv(resources.CACHE_ENV, str(tmp_path / "c"))
    assert resources.cache_dir() == tmp_path / "c"
    monkeypatch.delenv(resources.CACHE_ENV)
    import platformdirs

    assert resources.cache_dir() == Path(platformdirs.user_cache_dir("twin", appauthor=False))


def test_build_once_builds_then_reuses(tmp_path):
    calls = []

    def make(d: Path) -> None:
        calls.append(d)
        (d / "f.txt").write_text(str(len(calls)))

    target = tmp_path / "a" / "b"
    assert resources.build_once(target, make) == target
    assert resources.build_once(target, make) == target
    assert len(calls) == 1 and (target / "f.txt").read_text() == "1"
    resources.build_once(target, make, force=True)
    assert len(calls) == 2 and (target / "f.txt").read_text() == "2"
    assert sorted(p.name for p in target.parent.iterdir()) == ["b"]  # no temporary left


def test_a_concurrent_build_that_finishes_first_is_used(tmp_path):
    """Another process completes the same target while this one builds: its copy stays."""
    target = tmp_path / "t"

    def other(d: Path) -> None:
        (d / "who").write_text("other")

    def mine(d: Path) -> None:
        (d / "who").write_text("mine")
        resources.build_once(target, other)  # the other process, finishing first

    assert resources.build_once(target, mine) == target
    assert (target / "who").read_text() == "other"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t"]


def test_a_failed_build_leaves_nothing(tmp_path):
    def broken(d: Path) -> None:
        (d / "half").write_text("x")
        raise UserError("netconvert failed")

    with pytest.raises(UserError, match="netconvert failed"):
        resources.build_once(tmp_path / "t", broken)
    assert list(tmp_path.iterdir()) == []


def test_network_builds_go_to_the_cache_keyed_by_spec_and_sumo(tmp_path, monkeypatch):
    pytest.importorskip("sumo")
    from twin.sumo.network import build_dir, sumo_version

    monkeypatch.setenv(resources.CACHE_ENV, str(tmp_path))
    where = build_dir("shenzhen_like")
    assert where.parent == tmp_path / "networks" / "shenzhen_like"
    assert sumo_version() != "unknown"


# ------------------------------------------------------- cache entries checked before use
def _xml_entry(d: Path) -> None:
    (d / "a.net.xml").write_text('<?xml version="1.0"?>\n<!-- x -->\n<net version="1">\n</net>\n')
    (d / "a.trips.xml").write_text("<routes>\n  <trip id='0'/>\n</routes>\n")


def _verify(d: Path) -> None:
    resources.check_xml_files(d, {"a.net.xml": "net", "a.trips.xml": "routes"})


# name -> (how an existing entry is damaged, words of the one-line notice)
BROKEN_ENTRIES = {
    "a file deleted": (lambda d: (d / "a.trips.xml").unlink(), "a.trips.xml is missing"),
    "a file emptied": (lambda d: (d / "a.net.xml").write_bytes(b""), "a.net.xml is empty"),
    "a file cut short": (
        lambda d: (d / "a.net.xml").write_text('<net version="1">\n<edge id="e"'),
        "a.net.xml is cut short",
    ),
    "another kind of file": (
        lambda d: (d / "a.net.xml").write_text("<routes></routes>"),
        "a.net.xml is not a SUMO <net> file",
    ),
    "not XML at all": (lambda d: (d / "a.trips.xml").write_text("hello"), "a.trips.xml is not"),
    "another well-formed file": (
        lambda d: (d / "a.trips.xml").write_text("<routes>\n  <trip id='7'/>\n</routes>\n"),
        "a.trips.xml changed since it was built",
    ),
    "its record of the files damaged": (
        lambda d: (d / resources.SEAL).write_text("{"),
        f"{resources.SEAL}, the record of its files, is missing",
    ),
}


def test_a_whole_xml_file_may_end_with_a_comment(tmp_path):
    """A comment or processing instruction after the closing tag is whole XML, as SUMO reads
    it (it was called cut short: probe 26's u03)."""
    _xml_entry(tmp_path)
    with open(tmp_path / "a.net.xml", "a") as f:
        f.write("<!-- edited\n by hand -->\n<?stamp x?>\n")
    _verify(tmp_path)
    with open(tmp_path / "a.net.xml", "a") as f:  # what follows the comments is no XML
        f.write("<!---->" * 30 + "<edge")
    with pytest.raises(resources.BrokenEntry, match=r"a\.net\.xml is cut short"):
        _verify(tmp_path)


@pytest.mark.parametrize("case", list(BROKEN_ENTRIES))
def test_a_broken_cache_entry_is_rebuilt_and_reported(tmp_path, capsys, case):
    damage, needle = BROKEN_ENTRIES[case]
    target = tmp_path / "cache" / "entry"
    calls = []

    def make(d: Path) -> None:
        calls.append(d)
        _xml_entry(d)

    resources.build_once(target, make, verify=_verify)
    resources.build_once(target, make, verify=_verify)  # a good entry: reused
    assert len(calls) == 1 and capsys.readouterr().err == ""
    damage(target)
    assert resources.build_once(target, make, verify=_verify) == target
    err = capsys.readouterr().err.strip()
    assert len(calls) == 2 and "\n" not in err and err.startswith("twin: notice: cache entry")
    assert needle in err and "rebuilding it" in err
    _verify(target)  # whole again
    assert sorted(p.name for p in target.parent.iterdir()) == ["entry"]  # no temporary left


@pytest.mark.parametrize("generated_comment", [False, True])
def test_an_entry_of_an_earlier_twin_is_kept_when_a_fresh_build_agrees(
    tmp_path, capsys, generated_comment
):
    """An entry without a record of its files (built before twin kept one) is built again
    beside it; when the files agree (SUMO's "generated on" comment aside) the entry is kept as
    it is and sealed, not replaced: runs recorded on it still replay."""
    target = tmp_path / "cache" / "entry"
    calls = []

    def make(d: Path) -> None:
        calls.append(d)
        _xml_entry(d)

    resources.build_once(target, make, verify=_verify)
    (target / resources.SEAL).unlink()
    if generated_comment:  # as SUMO's tools wrote it before twin dropped the comment
        net = target / "a.net.xml"
        head, rest = net.read_bytes().split(b"\n", 1)
        net.write_bytes(head + b"\n<!-- generated on 2026-01-01 by netconvert -->\n" + rest)
    before = (target / "a.net.xml").read_bytes()
    assert resources.build_once(target, make, verify=_verify) == target
    assert len(calls) == 2 and capsys.readouterr().err == ""
    assert (target / resources.SEAL).is_file() and (target / "a.net.xml").read_bytes() == before
    assert sorted(p.name for p in target.parent.iterdir()) == ["entry"]  # no temporary left
    (target / "a.net.xml").write_text('<net version="2">\n</net>\n')  # now sealed: noticed
    resources.build_once(target, make, verify=_verify)
    assert len(calls) == 3 and "a.net.xml changed since it was built" in capsys.readouterr().err


def test_an_entry_without_its_seal_and_altered_is_reported_and_replaced(tmp_path, capsys):
    """Removing the seal does not make altered files trusted: the fresh build beside the entry
    differs, the entry is reported in one line and replaced by the build."""
    target = tmp_path / "cache" / "entry"

    def make(d: Path) -> None:
        _xml_entry(d)

    resources.build_once(target, make, verify=_verify)
    good = (target / "a.trips.xml").read_bytes()
    (target / resources.SEAL).unlink()
    (target / "a.trips.xml").write_text("<routes>\n  <trip id='7'/>\n</routes>\n")
    assert resources.build_once(target, make, verify=_verify) == target
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("twin: notice: cache entry")
    assert "a.trips.xml differs from a fresh build; replacing it" in err
    assert (target / "a.trips.xml").read_bytes() == good
    resources.check_seal(target)
    assert sorted(p.name for p in target.parent.iterdir()) == ["entry"]


def test_two_builds_of_an_entry_are_the_same_bytes(tmp_path):
    """The "generated on" comment SUMO's tools write (time, command, temporary folder) is
    dropped from a build, so a rebuilt entry equals the first one."""

    def make(d: Path) -> None:
        head = f'<?xml version="1.0"?>\n\n<!-- generated on {d.name} by netconvert\n<c/>\n-->\n\n'
        (d / "a.net.xml").write_text(head + '<net version="1">\n</net>\n')
        (d / "a.trips.xml").write_text("<routes>\n  <trip id='0'/>\n</routes>\n")

    one = resources.build_once(tmp_path / "one", make, verify=_verify)
    two = resources.build_once(tmp_path / "two", make, verify=_verify)
    assert (one / "a.net.xml").read_bytes() == (two / "a.net.xml").read_bytes()
    assert (one / "a.net.xml").read_text() == '<?xml version="1.0"?>\n\n<net version="1">\n</net>\n'


def test_a_file_where_an_entry_belongs_is_replaced_by_the_entry(tmp_path, capsys):
    target = tmp_path / "cache" / "entry"
    target.parent.mkdir()
    target.write_text("not a folder")
    assert resources.build_once(target, _xml_entry, verify=_verify) == target
    _verify(target)
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "is a file, not a folder; rebuilding it" in err


def test_a_broken_build_is_not_committed(tmp_path):
    def half(d: Path) -> None:
        _xml_entry(d)
        (d / "a.trips.xml").write_text("<routes><trip id='0'/>")

    with pytest.raises(UserError, match=r"broken entry \(a.trips.xml is cut short"):
        resources.build_once(tmp_path / "t", half, verify=_verify)
    assert list(tmp_path.iterdir()) == []  # nothing renamed in, no temporary left


def test_generated_demand_in_the_cache_is_rebuilt_when_damaged(tmp_path, monkeypatch, capsys):
    """A network without demand gets generated trips in the cache; emptied, they are
    rebuilt on the next use with a one-line notice."""
    pytest.importorskip("libsumo")
    from twin.config import load_config
    from twin.sumo.network import generate_grid_scenario
    from twin.sumo.scenario import sumo_source

    monkeypatch.setenv(resources.CACHE_ENV, str(tmp_path / "cache"))
    generate_grid_scenario(tmp_path, 3, 300, 300, 5.0, 1)
    (tmp_path / "c.toml").write_text(
        '[swarm]\nn_drones = 1\n[traffic]\nkind = "sumo"\nnet = "small.net.xml"\n'
        'cell_m = 200.0\ndrone_speed_kmh = 12.0\nbegin = "07:00"\nwarmup_min = 1.0\n'
        "horizon = 2\n"
    )
    first = sumo_source(load_config(tmp_path / "c.toml")).scenario.route_files[-1]
    assert first.is_relative_to(tmp_path / "cache" / "imported")
    good = first.read_bytes()
    capsys.readouterr()
    first.write_bytes(b"")
    again = sumo_source(load_config(tmp_path / "c.toml")).scenario.route_files[-1]
    err = capsys.readouterr().err
    import xml.etree.ElementTree as ET

    def trips(data: bytes) -> list[dict]:
        return [t.attrib for t in ET.fromstring(data).iter("trip")]

    assert again == first and trips(again.read_bytes()) == trips(good)  # same seed, same trips
    assert "(rush_hour.trips.xml is empty); rebuilding it" in err and err.count("\n") == 1


def test_a_damaged_network_build_is_rebuilt(tmp_path, monkeypatch, capsys):
    """The built-in network's cache entry is checked on use: with its trips file cut short
    (or its build stamp of another spec) it is rebuilt, with a one-line notice. netconvert and
    the demand are stubbed: this checks the wiring, test_sumo_network the build itself."""
    pytest.importorskip("sumo")
    import twin.sumo.demand as demand
    import twin.sumo.network as network

    monkeypatch.setenv(resources.CACHE_ENV, str(tmp_path))
    builds = []

    def fake_netconvert(args, what):
        out = Path(args[args.index("--output-file") + 1])
        out.write_text('<net version="1.20">\n</net>\n')
        builds.append(out)

    def fake_demand(net, spec, out, seed):
        out.write_text("<routes>\n</routes>\n")

    monkeypatch.setattr(network, "run_sumo_program", fake_netconvert)
    monkeypatch.setattr(demand, "write_spec_demand", fake_demand)
    first = network.build_named_network("shenzhen_like")
    assert network.build_named_network("shenzhen_like") == first and len(builds) == 1
    first.trips_file.write_text("<routes>\n<trip id='0'")
    again = network.build_named_network("shenzhen_like")
    err = capsys.readouterr().err.strip()
    assert len(builds) == 2 and again.trips_file.read_text() == "<routes>\n</routes>\n"
    assert err.startswith("twin: notice: cache entry") and "\n" not in err
    assert "shenzhen_like.trips.xml is cut short" in err
    stamp = first.net_file.parent / "build.json"
    stamp.write_text('{"spec_hash": "another"}')
    network.build_named_network("shenzhen_like")
    assert len(builds) == 3 and "build.json does not match the spec" in capsys.readouterr().err


def test_an_unsealed_entry_with_two_generator_comments_is_kept(tmp_path, capsys):
    """randomTrips' route file holds two "generated on" comments (its own and duarouter's,
    each with the time and the temporary folder): both are dropped, so an entry without its
    seal equals a fresh build and is kept, not "replaced" at every run (probe 14's f02)."""

    def make(d: Path) -> None:
        head = '<?xml version="1.0"?>\n\n'
        for tool in ("randomTrips", "duarouter"):
            head += f"<!-- generated on {d.name} by {tool}\n<c/>\n-->\n\n"
        (d / "a.net.xml").write_text('<net version="1">\n</net>\n')
        (d / "a.trips.xml").write_text(head + "<routes>\n  <trip id='0'/>\n</routes>\n")

    target = tmp_path / "entry"
    resources.build_once(target, make, verify=_verify)
    assert b"generated on" not in (target / "a.trips.xml").read_bytes()
    (target / resources.SEAL).unlink()
    capsys.readouterr()
    resources.build_once(target, make, verify=_verify)
    assert "differs" not in capsys.readouterr().err
    resources.check_seal(target)


@pytest.mark.parametrize("linked", [False, True])
def test_the_scratch_sweep_removes_only_twins_own_stale_entries(tmp_path, monkeypatch, linked):
    """Old entries of the cache's tmp/ are removed only when twin made them (named twin-...):
    a user's files lying there are kept (probe 17's P2-04: every entry older than two days was
    deleted); a tmp link is refused in one line, and nothing behind it is touched."""
    import os
    import time

    cache = tmp_path / "cache"
    cache.mkdir()
    scratch = tmp_path / "elsewhere" if linked else cache / "tmp"
    (scratch / "project").mkdir(parents=True)
    if linked:
        (cache / "tmp").symlink_to(scratch)
    (scratch / "notes.txt").write_text("precious")
    (scratch / "project" / "thesis.tex").write_text("work")
    (scratch / "twin-sumo-dead.log").write_text("a killed run's")
    (scratch / "twin-frames-dead").mkdir()
    (scratch / "twin-sumo-fresh.log").write_text("a running one's")
    old = time.time() - (resources.SCRATCH_DAYS + 1) * 86400
    for name in ("notes.txt", "project/thesis.tex", "project", "twin-sumo-dead.log",
                 "twin-frames-dead"):  # fmt: skip
        os.utime(scratch / name, (old, old))
    monkeypatch.setenv("TWIN_CACHE_DIR", str(cache))
    monkeypatch.setattr(resources, "_SWEPT", set())
    if linked:  # twin writes only into its cache: not through a link out of it
        with pytest.raises(UserError, match=r"tmp: twin's scratch folder is a link \(to .*"
                                            r"elsewhere\).*remove the link") as info:  # fmt: skip
            resources.scratch_dir()
        assert "\n" not in str(info.value)
        assert len(list(scratch.iterdir())) == 5  # nothing removed
        return
    resources.scratch_dir()
    assert sorted(p.name for p in scratch.iterdir()) == [
        "notes.txt", "project", "twin-sumo-fresh.log"
    ]  # fmt: skip
    assert (scratch / "project" / "thesis.tex").read_text() == "work"


def test_a_shared_ray_folder_loses_only_the_sessions_of_ended_processes(tmp_path, monkeypatch):
    """``tmp/twin-ray`` is shared by every local Ray: never removed whole by age (a long
    sweep's live session went with it), each ``session_..._<pid>`` removed once its process
    has ended (those of killed runs stayed for good), and a link that leads nowhere."""
    import os
    import time

    cache = tmp_path / "cache"
    ray = cache / "tmp" / "twin-ray"
    live, dead = ray / f"session_2026_{os.getpid()}", ray / "session_2026_999999999"
    elsewhere = ray / "session_2025_999999998"  # another machine's (a shared cache), young
    for session in (live, dead, elsewhere):
        (session / "sockets").mkdir(parents=True)
        (session / resources.HOST_MARK).write_text(resources.host_mark())
    (elsewhere / resources.HOST_MARK).write_text("another-host pid:[1]")
    (ray / "session_latest").symlink_to(dead)
    old = time.time() - (resources.SCRATCH_DAYS + 1) * 86400
    for path in (ray, live):
        os.utime(path, (old, old))
    monkeypatch.setenv("TWIN_CACHE_DIR", str(cache))
    monkeypatch.setattr(resources, "_SWEPT", set())
    resources.scratch_dir()
    assert sorted(p.name for p in ray.iterdir()) == sorted([live.name, elsewhere.name])
    os.utime(elsewhere, (old, old))  # another host's, once old
    monkeypatch.setattr(resources, "_SWEPT", set())
    resources.scratch_dir()
    assert sorted(p.name for p in ray.iterdir()) == [live.name]

"""The live SUMO traffic source: SUMO advances in lockstep with the swarms (Sec. IV-B).

Each swarm step advances SUMO by ``cell size / drone speed`` (500 m at 24 km/h = 75 s). A drone
that spends a step over a cell sees the whole interval, so the source reads every vehicle's
position and speed at ``reads_per_step`` instants evenly spread over the step, the last at the
sample time (one bulk read each, no subscriptions), bins them into cells
(:mod:`twin.sumo.cells`) and keeps per cell the vehicle-instants and their mean speed: Edie's
definitions over the step instead of one instant, which removes the aliasing of signal cycles
by a 75 s sampling (benchmarks/bench_sumo.py --aliasing). The MFD observation model
(:class:`twin.mfd.MFDImportance`) turns them into ``T^k``. Scheduled incidents
(:mod:`twin.sumo.incidents`) are applied at their times. A warm-up before ``T^0`` fills the network and gives the
online MFD fit its first samples. Everything read is kept: the traffic tape (counts and speeds
of every cell at every sample time) and the MFD samples, also after a SUMO failure mid-run.
"""

from __future__ import annotations

import time
from collections.abc import Generator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twin.clock import clock_label
from twin.errors import UserError
from twin.files import file_sha256
from twin.grid import Grid
from twin.mfd import MFD, MFDImportance, density_from_occupancy
from twin.sumo.cells import CellGeometry
from twin.sumo.detectors import DETECTOR_COLUMNS, DetectorPlan
from twin.sumo.incidents import configured_schedule
from twin.sumo.readers import (
    as_given,
    file_list,
    included_files,
    naming_the_sumocfg,
    read_sumocfg,
)
from twin.sumo.session import SumoRunError, SumoSession, filled_in_options
from twin.timing import (
    DETECTOR_READS,
    OBSERVATION,
    READS,
    SUMO_STEPPING,
    SUMO_WARMUP,
    WAITING_FOR_SUMO,
    StageTimer,
)
from twin.traffic.base import TrafficSource


@dataclass
class SumoScenario:
    """Everything a live SUMO run needs (built from a config by :mod:`twin.sumo.scenario`)."""

    net_file: Path
    route_files: list[Path]
    begin_s: float = 25200.0  # time of T^0 (07:00)
    warmup_s: float = 1800.0  # simulated before T^0
    step_s: float = 75.0  # cell size / drone speed
    horizon: int = 144
    seed: int = 0
    mesoscopic: bool = False
    mfd_fit: str = "online"
    detection_p: float = 1.0
    name: str = "sumo"
    sumocfg: Path | None = None
    mfd_prior: tuple[float, float] = (0.7, 40.0)  # (a, k_c): the prior, or the fixed MFD
    sumo_options: tuple[str, ...] = ()  # more SUMO options (e.g. --fcd-output in tests)
    reads_per_step: int = 1  # read instants per step, the last at the sample time
    incidents: list[Any] = field(default_factory=list)  # IncidentSettings (twin.config)
    detectors: DetectorPlan = field(default_factory=DetectorPlan)  # fixed detectors read
    #: lanes cars may not use (bike, bus, rail lanes): their vehicles are not counted
    not_for_cars: frozenset[str] = frozenset()
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def sim_begin(self) -> float:
        return self.begin_s - self.warmup_s

    @property
    def sim_end(self) -> float:
        return self.begin_s + self.horizon * self.step_s

    def warmup_steps(self) -> int:
        return int(self.warmup_s / self.step_s + 1e-9)

    def read_offsets(self) -> list[float]:
        """Seconds before each sample time of its read instants, whole SUMO steps, last 0."""
        from twin.traffic.tape import read_offsets

        return read_offsets(self.step_s, self.reads_per_step)


#: Options of a sumocfg that name further input files SUMO reads (a saved state, edge weights):
#: part of a run's identity.
SUMOCFG_INPUTS = ("load-state", "weight-files")


class SumoTraffic(TrafficSource):
    """``T^0 .. T^horizon`` from a SUMO run advanced as the maps are pulled."""

    keeps_partial_results = True
    live = True
    waiting_stage = WAITING_FOR_SUMO
    process_name = "sumo"

    def __init__(self, scenario: SumoScenario, geometry: CellGeometry, grid: Grid):
        self.scenario = scenario
        self.geometry = geometry
        self.grid = grid
        self.horizon = scenario.horizon
        self.model = self._model()
        self.snapshots: list[tuple[int, float, np.ndarray, np.ndarray]] = []
        self.error: str | None = None
        self.vehicles_seen: list[int] = []
        self.read_seconds = 0.0
        self.incident_schedule = None
        #: wall time of SUMO stepping, reads and binning, the observation model (per run)
        self.timer = StageTimer()
        #: a :class:`twin.sumo.gui.GuiSettings` to run under sumo-gui (``--gui``); None: libsumo
        self.gui = None
        #: run SUMO (and the observation model) in a child process that works ahead while the
        #: swarms decide, on the other core (set by the experiment runner for live runs)
        self.separate_process = False
        #: keep SUMO open when the maps end, for :meth:`close_deferred` (the SUMO child sends
        #: the run's end state first)
        self.defer_close = False
        #: SUMO's messages go to ``sumo-messages.log`` (the SUMO child): its warnings with them
        self.messages_kept = False
        self._closing: tuple[Any, Path | None] | None = None
        self._truth: np.ndarray | None = None
        self._incidents: list[dict[str, Any]] | None = None
        #: where SUMO's configured outputs go (the run folder's ``sumo/``); None: a temporary
        #: folder removed when the run ends (never beside the scenario's files)
        self.output_dir: Path | None = None
        #: the output files and rewritten additional files of the last run
        self.outputs: list[Path] = []
        #: the names of the outputs the scenario's files ask SUMO for (the last run)
        self.asked_outputs: list[str] = []
        self._copies: dict[Path, Path] = {}  # rewritten additional file -> the user's
        #: the fixed detectors read (:mod:`twin.sumo.detectors`) and their readings per step:
        #: ``(k, detector index, vehicles, occupancy %, mean speed, importance)``
        self.detectors: list = []
        self.detector_readings: list[tuple[int, int, int, float, float, float]] = []

    def _model(self) -> MFDImportance:
        g, s = self.geometry, self.scenario
        return MFDImportance(
            self.grid.free,
            g.lane_km,
            g.speed_limit,
            s.mfd_fit,
            MFD(*s.mfd_prior),
            s.detection_p,
            s.seed,
            s.reads_per_step,
        )

    def model_after(self, snapshots: list) -> MFDImportance:
        """The MFD model as it stood after ``snapshots`` (a run stopped while its SUMO child
        worked ahead): a fresh model fed them again, as a replay of the tape does."""
        model = self._model()
        for k, _, count, speed in snapshots:
            model.observe(k, count, speed.astype(float))
        return model

    def session(self, output_dir: Path | None = None) -> SumoSession:
        """The SUMO session of a run; with ``output_dir``, the scenario's configured outputs
        (sumocfg options, additional files' detectors ...) are written there
        (:mod:`twin.sumo.outputs`)."""
        s = self.scenario
        options, route_files = tuple(s.sumo_options), list(s.route_files)
        net_file = s.net_file
        if output_dir is not None:
            from twin.sumo.outputs import naming_that_fits, redirect_outputs

            options, plan = redirect_outputs(s.sumocfg, options, output_dir)
            route_files = [plan.routes(r) for r in route_files]
            net_file = plan.network(net_file)
            options = naming_that_fits(plan.device_defaults(options), plan)  # every file known
            self._copies = {c: o for o, c in plan.copies.items() if c != o}
            written = [*plan.targets.values(), *plan.made.values()]
            self.outputs = [*written, *self._copies]
            self.asked_outputs = sorted(p.name for p in written)
            if s.detectors.loops:
                from twin.sumo.detectors import with_additional, write_loops

                loops = write_loops(s.detectors.loops, plan.own_file("twin-loops.add.xml"),
                                    s.step_s)  # fmt: skip
                options = with_additional(options, loops)
                self.outputs.append(loops)
        return SumoSession(
            net_file=net_file,
            route_files=route_files,
            begin=s.sim_begin,
            end=s.sim_end + 1.0,
            seed=s.seed,
            mesoscopic=s.mesoscopic,
            config_file=s.sumocfg,
            # twin's own demand, or closures it schedules, which leave routes unfollowable
            ignore_route_errors=bool(s.extra.get("twin_demand", True) or s.incidents),
            extra_options=(*filled_in_options(s.sumocfg), *options),
            gui=self.gui,
            warnings=self.messages_kept,
        )

    def sample_times(self) -> list[tuple[int, float]]:
        """``(step, time)`` of every snapshot: warm-up steps are negative, ``T^k`` at step k."""
        s = self.scenario
        w = s.warmup_steps()
        times = [(k, round(s.begin_s + k * s.step_s, 3)) for k in range(-w, s.horizon + 1)]
        # nothing to read at the start, but T^0 itself (no warm-up: the network as it begins)
        return [(k, t) for k, t in times if t > s.sim_begin or k == 0]

    def sighting_model(self):
        """The drones count the vehicles of each cell's lanes through the scenario's detection
        probability, reads per step and MFD prior (:class:`twin.belief.SightingModel`)."""
        from twin.belief import SightingModel

        s = self.scenario
        return SightingModel(
            s.detection_p,
            np.asarray(self.geometry.lane_km, dtype=float).ravel(),
            float(s.mfd_prior[1]),
            int(s.reads_per_step),
        )

    def truth_map(self):
        """The true ``T^k`` of the map last yielded, when vehicles may be missed (detection
        probability below 1): the same MFD on every vehicle."""
        if self.separate_process:
            return self._truth
        return self.model.truth if self.model.detection_p < 1.0 else None

    def importance_maps(self) -> Generator[np.ndarray, None, None]:
        """``T^0 .. T^horizon``; in a forked child process when :attr:`separate_process` (on
        Linux, not under sumo-gui, nor inside a daemonic process, which may have no children)."""
        import multiprocessing
        import sys

        if (
            self.separate_process
            and self.gui is None
            and sys.platform.startswith("linux")
            and not multiprocessing.current_process().daemon
        ):
            from twin.sumo.worker import maps_from_child

            return maps_from_child(self)
        self.separate_process = False
        return self.maps_here()

    def _users_refusal(self, exc: UserError) -> UserError:
        """SUMO's refusal naming the user's file, not twin's rewritten copy of it, and the
        sumocfg that names it."""
        s = self.scenario
        message = str(exc)
        for copy, original in self._copies.items():
            message = message.replace(str(copy), str(original))
        listed = [Path(f) for f in s.extra.get("sumocfg_files", [])]
        return UserError(naming_the_sumocfg(message, s.sumocfg, listed))

    def maps_here(self, warmup_too: bool = False) -> Generator[np.ndarray | None, None, None]:
        """The maps, SUMO running in this process; with ``warmup_too`` also a None after each
        snapshot of the warm-up (SUMO's child sends every snapshot on as it is read)."""
        from twin.sumo.incidents import IncidentSchedule

        s = self.scenario
        self.model = self._model()
        self.snapshots, self.error = [], None
        stepped = False  # a snapshot of a step k >= 1 was read: a partial run has one to keep
        self.timer = timer = StageTimer()
        self.incident_schedule = IncidentSchedule(s.incidents, self.geometry, s, self.grid)
        offsets = s.read_offsets()
        first_read = s.sim_begin + 1.0  # the earliest instant with a state to read
        clock = time.perf_counter
        t_start = clock()
        scratch = None
        if self.output_dir is None:
            import tempfile

            from twin.resources import scratch_dir

            scratch = Path(tempfile.mkdtemp(prefix="twin-sumo-", dir=scratch_dir()))
        try:
            session = self.session(self.output_dir or scratch).start()
        except UserError as exc:
            _remove(scratch)
            raise self._users_refusal(exc) from None
        except BaseException:
            _remove(scratch)
            raise
        if scratch is not None and self.asked_outputs:
            from twin.boundary import notify

            notify(
                f"twin: notice: {s.name}: the outputs its files ask SUMO for ({', '.join(self.asked_outputs[:4])}"
                f"{' ...' if len(self.asked_outputs) > 4 else ''}) are not kept by this command "
                "(it keeps no SUMO outputs); `twin run` keeps them in RUN/sumo/"
            )
        timer.add(SUMO_WARMUP, clock() - t_start)
        reader = None
        self.detector_readings = []
        if s.detectors.active:
            from twin.sumo.detectors import scenario_reader
            from twin.sumo.session import _libsumo

            reader = scenario_reader(s, self.geometry, _libsumo())
            self.detectors = reader.detectors
        try:
            for k, t in self.sample_times():
                t_snapshot = clock()
                stepping = reading = 0.0
                count = np.zeros(self.grid.shape, dtype=np.int64)
                distance = np.zeros(self.grid.shape)
                for offset in offsets:
                    instant = max(t - offset, min(first_read, t))
                    t0 = clock()
                    try:
                        self.incident_schedule.advance_to(session, instant)
                    except SumoRunError as exc:
                        # no step to keep, and SUMO's own error (libsumo's; under sumo-gui it
                        # may be its window closed): the input SUMO refused, as on start
                        if self.gui is None and not stepped:
                            when = f" before the window's first step (t = {instant:g} s)"
                            refusal = session.refusal(exc.reason, when)
                            raise self._users_refusal(refusal) from None
                        where = session.file_of(exc.reason) if self.gui is None else None
                        said = f"{where}: {exc}" if where is not None else str(exc)
                        self.error = str(self._users_refusal(UserError(said)))
                        raise SumoRunError(self.error, exc.reason) from exc
                    t1 = clock()
                    xy, speed = session.vehicles(s.not_for_cars)
                    n, v = self.geometry.count_and_speed(xy, speed)
                    count += n
                    distance += np.nan_to_num(v) * n
                    t2 = clock()
                    stepping += t1 - t0
                    reading += t2 - t1
                self.read_seconds += reading
                self.vehicles_seen.append(len(xy))  # at the sample time
                if len(offsets) == 1:
                    mean_speed = v  # one read: as read, bit for bit
                else:
                    with np.errstate(invalid="ignore", divide="ignore"):
                        mean_speed = np.where(count > 0, distance / np.maximum(count, 1), np.nan)
                # The model sees exactly what the tape keeps (float32 speeds), so replays match.
                count, mean_speed = count.astype(np.int32), mean_speed.astype(np.float32)
                self.snapshots.append((k, t, count, mean_speed))
                stepped = stepped or k >= 1
                t_detectors = clock()
                if reader is not None and k >= 0:
                    self._read_detectors(reader, k)
                    timer.add(DETECTOR_READS, clock() - t_detectors)
                t3 = clock()
                importance = self.model.observe(k, count, mean_speed.astype(float))
                if k < 0:
                    timer.add(SUMO_WARMUP, clock() - t_snapshot, calls=0)
                    if warmup_too:
                        yield None
                else:
                    timer.add(SUMO_STEPPING, stepping)
                    timer.add(READS, reading + (t3 - t2))
                    timer.add(OBSERVATION, clock() - t3)
                    yield importance
        finally:
            if self.defer_close:  # the SUMO child closes it after sending its end state
                self._closing = (session, scratch)
            else:
                session.close()
                _remove(scratch)

    def close_deferred(self) -> None:
        """Close SUMO after a run whose maps ended with :attr:`defer_close` set (the SUMO
        child sends the run's end state first: a crash in SUMO's teardown loses nothing)."""
        session, scratch = self._closing or (None, None)
        self._closing = None
        if session is not None:
            session.close()
            _remove(scratch)

    def _read_detectors(self, reader, k: int) -> None:
        """Step ``k``'s new detector readings, their importance by the MFD in effect (the one
        that observes this step's snapshot)."""
        rows = reader.read()
        if rows:
            occupancy = np.array([r[2] for r in rows])
            importance = self.model.mfd.importance(density_from_occupancy(occupancy))
            self.detector_readings += [
                (k, n, count, occ, speed, float(imp))
                for (n, count, occ, speed), imp in zip(rows, importance, strict=True)
            ]

    def detector_observations(self):
        """The readings as :class:`twin.belief.DetectorObservations` (None without detectors)."""
        if not self.scenario.detectors.active:
            return None
        from twin.belief import DetectorObservations

        cells = [d.cell for d in self.detectors]
        return DetectorObservations.from_readings(
            [(k, cells[n][0] * self.grid.ny + cells[n][1], imp)
             for k, n, _, _, _, imp in self.detector_readings],
            self.horizon,
        )  # fmt: skip

    def detector_table(self):
        """``detectors.parquet``'s rows of this run: one per reading, with the detector."""
        import pandas as pd

        rows = []
        for k, n, count, occ, speed, imp in self.detector_readings:
            d = self.detectors[n]
            rows.append({"step": k, "detector": d.id, "kind": d.kind, "virtual": d.virtual,
                         "lane": d.lane, "i": d.cell[0], "j": d.cell[1], "vehicles": count,
                         "occupancy_pct": occ, "speed": speed, "importance": imp})  # fmt: skip
        return pd.DataFrame(rows, columns=DETECTOR_COLUMNS)

    def incidents_info(self) -> list[dict[str, Any]]:
        """The scheduled incidents as applied so far (``incidents.json``)."""
        if self._incidents is not None:  # as the SUMO process applied them
            return self._incidents
        if self.incident_schedule is None:
            return []
        return self.incident_schedule.to_json()

    def clock(self, k: int) -> str | None:
        return clock_label(self.scenario.begin_s + k * self.scenario.step_s)

    def warmup_steps(self) -> int:
        return self.scenario.warmup_steps()

    def coarser_hint(self, ratio: float) -> str | None:
        """A cell size (rounded up to 50 m) about ``ratio`` times larger, or fewer steps (a
        shorter warm-up when its snapshots outnumber the steps: they are kept too)."""
        cell = float(np.ceil(self.geometry.cell_m * ratio / 50.0) * 50.0)
        warmup = self.warmup_steps()
        fewer = (
            f"a shorter warm-up ([traffic].warmup_min: its {warmup} snapshots are kept)"
            if warmup > self.horizon
            else "fewer steps (--horizon)"
        )
        return f"cells of {cell:g} m (--cell-m, [traffic].cell_m) or {fewer}"

    def metadata(self) -> dict[str, Any]:
        s = self.scenario
        return {
            "kind": "sumo",
            "name": s.name,
            "horizon": self.horizon,
            "net_file": str(s.net_file),
            "route_files": [str(p) for p in s.route_files],
            "sumocfg": str(s.sumocfg) if s.sumocfg else None,
            "begin": clock_label(s.begin_s),
            "warmup_s": s.warmup_s,
            "step_s": s.step_s,
            "seed": s.seed,
            "mesoscopic": s.mesoscopic,
            "mfd_fit": s.mfd_fit,
            "mfd_prior": list(s.mfd_prior),
            "detection_p": s.detection_p,
            "reads_per_step": s.reads_per_step,
            "read_offsets_s": s.read_offsets(),
            "error": self.error,
            "sumo_outputs": self.output_files(),
            "incidents": configured_schedule(s.incidents),
            "identity": self.identity(),
        }

    def identity(self) -> dict[str, Any]:
        """What a replay of this run must find unchanged: the network file (sha256), every file
        SUMO loads (sha256 of the network, route, additional and sumocfg files, generated demand
        included), the cell size, the grid's shape, SUMO's and twin's versions (``run.json``
        traffic.identity)."""
        if "net_sha256" not in self.scenario.extra:
            self.scenario.extra["net_sha256"] = file_sha256(self.scenario.net_file)
        from twin import __version__
        from twin.sumo.network import sumo_version

        return {
            "net_sha256": self.scenario.extra["net_sha256"],
            "files": self.input_hashes(),
            "cell_m": float(self.geometry.cell_m),
            "grid": [int(self.grid.nx), int(self.grid.ny)],
            "sumo": sumo_version(),
            "twin": __version__,
        }

    def input_files(self) -> list[tuple[str, Path]]:
        """``(role, path)`` of every file SUMO loads for this scenario, absolute (a replay from
        another folder finds the same names)."""
        s = self.scenario
        files = [("network", Path(s.net_file))]
        for r in s.route_files:
            files.append(("route file", Path(r)))
            files += [("included file", p) for p in included_files(Path(r)) if p.is_file()]
        for a in s.extra.get("additional_files", []):
            files.append(("additional file", Path(a)))
            files += [("included file", p) for p in included_files(Path(a)) if p.is_file()]
        if s.sumocfg is not None:
            files.append(("sumocfg", Path(s.sumocfg)))
            options = read_sumocfg(Path(s.sumocfg), own_net=False).options
            for name in SUMOCFG_INPUTS:  # other files the config makes SUMO read
                for p in file_list(options.get(name), Path(s.sumocfg).parent, Path(s.sumocfg)):
                    if p.is_file():
                        files.append((name, p))
        return [(role, as_given(path)) for role, path in files]  # `..` after a link: its target's

    def input_hashes(self) -> list[dict[str, str]]:
        """``{"role", "path", "sha256"}`` of every file SUMO loads (hashed once per file and
        version, streamed)."""
        return [
            {"role": role, "path": str(path), "sha256": file_sha256(path)}
            for role, path in self.input_files()
        ]

    def output_files(self) -> list[str]:
        """SUMO's configured outputs (and rewritten additional files) written into the output
        folder, relative to it."""
        d = self.output_dir
        if d is None or not Path(d).is_dir():
            return []
        return sorted(p.relative_to(d).as_posix() for p in Path(d).rglob("*") if p.is_file())

    def network_info(self) -> dict[str, Any]:
        """``network.json``: the net file, the grid's placement and cell size, the bbox."""
        s = self.scenario
        return {
            "name": s.name,
            "net_file": str(s.net_file),
            "route_files": [str(p) for p in s.route_files],
            "grid": self.geometry.to_json(),
            "n_obstacles": int(self.grid.obstacles.sum()),
            "row_0": "north",
        }

    def tape(self):
        """The traffic tape of what was read so far (see :mod:`twin.traffic.tape`)."""
        from twin.traffic.tape import Tape

        return Tape.from_source(self)

    def write_extras(self, run_dir: Path, by_seed: Sequence[tuple[int, TrafficSource]]) -> None:
        """``network.json``, the MFD fit and samples, ``incidents.json`` (if any) and the tape
        of this seed (``tape.parquet``); with several seeds every seed's tape in ``tapes/``."""
        import pandas as pd

        from twin.files import atomic_write, nan_as_null, write_json

        write_json(run_dir / "network.json", self.network_info())
        write_json(run_dir / "mfd.json", nan_as_null(self.model.report()))
        if self.incidents_info():
            write_json(run_dir / "incidents.json", self.incidents_info())
        samples = pd.DataFrame(self.model.samples())
        atomic_write(run_dir / "mfd_samples.parquet", lambda p: samples.to_parquet(p, index=False))
        atomic_write(run_dir / "tape.parquet", self.tape().write)
        if self.scenario.detectors.active:
            table = pd.concat(
                [src.detector_table().assign(seed=seed) for seed, src in by_seed
                 if isinstance(src, SumoTraffic)], ignore_index=True,
            )[DETECTOR_COLUMNS]  # fmt: skip
            atomic_write(run_dir / "detectors.parquet", lambda p: table.to_parquet(p, index=False))
        if len(by_seed) > 1:
            (run_dir / "tapes").mkdir(exist_ok=True)
            for seed, source in by_seed:
                atomic_write(run_dir / "tapes" / f"seed-{seed}.parquet", source.tape().write)


def _remove(folder: Path | None) -> None:
    if folder is not None:
        import shutil

        shutil.rmtree(folder, ignore_errors=True)

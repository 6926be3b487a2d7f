"""The experiment runner: one place that turns a scenario into results.

Every command that runs swarms goes through here: ``twin evaluate``, ``twin run``, a sweep
cell, the learning-curve tool and the benchmarks. An :class:`Experiment` names a scenario
config, the swarms (with options on top of the config's ``[swarm_options]``), the seeds and
where the traffic comes from (the config's own traffic, a replayed tape, or a live simulation
with swapped-in files); :func:`run_experiment` builds the traffic source
(:mod:`twin.traffic_kinds`) and the swarms and runs one patrol pass per seed;
:func:`twin.runs.record` writes the run folder.

Seeds: seed ``s`` fixes the drones' starts (``default_rng(s)``) and the swarms' randomness
(:func:`twin.patrol.swarm_rng`). Live traffic is simulated once per seed, the n-th seed with
traffic seed ``traffic_seed + n`` (``traffic_seed`` defaults to ``[traffic].seed``);
synthetic and replayed traffic is the same for every seed.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from twin.boundary import count_said, drop_notices, hold_notices, notify, release_notices
from twin.config import ScenarioConfig, check_faults, check_swarm_fits, start_positions
from twin.errors import UserError
from twin.patrol import INTERRUPTED, PatrolResult, run_patrol
from twin.policies import Policy
from twin.processes import STOP_ASKED, interrupt_on_terminate
from twin.swarms import check_swarm_name, is_learned
from twin.traffic.base import TrafficSource
from twin.traffic_kinds import build_traffic, is_live_kind


@dataclass
class Experiment:
    """What to run: a scenario, swarms, seeds and the traffic's origin."""

    config: ScenarioConfig
    swarms: Sequence[str]
    seeds: Sequence[int]
    #: keyword options per swarm, applied over the config's ``[swarm_options.<swarm>]``
    swarm_options: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    tape: Path | None = None  # replay a recorded traffic tape instead of the config's traffic
    #: options of the live traffic's builder (``twin run``'s swapped-in files)
    traffic_options: Mapping[str, Any] = field(default_factory=dict)
    traffic_seed: int | None = None  # live traffic's seed of the first seed ([traffic].seed)
    #: learned swarms that cannot be built (no torch, no checkpoint) are skipped with a notice
    skip_unavailable: bool = False
    keep_importance: bool = True
    #: refuse a run whose estimated memory exceeds this (GB); None: $TWIN_MAX_MEMORY_GB or 8
    max_memory_gb: float | None = None
    #: live traffic in a process of its own, ahead of the swarms; same results
    separate_process: bool = True
    #: seeds run at once, each in a worker process of its own with its traffic (a live
    #: simulation) and swarms (:func:`run_experiment`); 1: one after another in this process.
    #: Same results.
    workers: int = 1
    executor: str = "local"  # where the workers run: a local process pool, or "ray"
    #: where a live source writes its scenario's configured outputs: the first seed's in this
    #: folder, the others' in ``seed-<s>/`` under it; None: a temporary folder
    outputs_dir: Path | None = None


@dataclass
class ExperimentResult:
    experiment: Experiment
    results: list[PatrolResult]
    traffic: list[dict[str, Any]]  # metadata of each seed's traffic source
    policies: dict[str, dict[str, Any]]  # what each swarm says of itself (checkpoint, options)
    seconds: float
    #: the live sources of each seed, kept open only when ``keep_sources`` was asked for
    sources: list[TrafficSource] = field(default_factory=list)
    #: stopped by Ctrl-C (:func:`stop_on_interrupt`): the results hold the steps done so far
    interrupted: bool = False
    #: a later seed that stopped before its last step (Ctrl-C, a simulation that failed): left
    #: out of ``results`` (:func:`leave_out_unfinished_seed`)
    left_out: PatrolResult | None = None
    #: every seed left out, ``left_out``'s among them, with the steps it ran (seeds run at
    #: once and stopped by Ctrl-C at different steps: those that ran fewer than the longest)
    left_out_seeds: dict[int, int] = field(default_factory=dict)

    @property
    def partial(self) -> bool:
        return self.interrupted or self.left_out is not None or any(r.error for r in self.results)

    @property
    def stopped(self) -> PatrolResult:
        """The seed the run ended with: the one left out, else the last."""
        return self.left_out or self.results[-1]

    def partial_reason(self) -> str | None:
        """Why a seed is missing from the results, for ``run.json``."""
        r = self.left_out
        if r is None:
            return None
        planned = self.results[0].completed_steps
        kept = seed_ranges([k.seed for k in self.results])
        seeds = f"seed{'s' if len(self.results) > 1 else ''} {kept}"
        steps = {**self.left_out_seeds, r.seed: r.completed_steps}
        span = "every step"
        if self.results[0].error:  # seeds run at once, stopped at different steps
            span = f"{planned} step{'s' * (planned != 1)}" + " each" * (len(self.results) > 1)
        if len(steps) > 1 or self.results[0].error:
            ran = ", ".join(f"{seed} after {steps[seed]}" for seed in sorted(steps))
            return (
                f"seed{'s' * (len(steps) > 1)} {ran} stopped before step {planned}: left out, "
                f"the tables hold {seeds} ({span})"
            )
        why = r.error or f"stopped after {r.completed_steps} of {planned} steps"
        return f"seed {r.seed}: {why}; left out, the tables hold {seeds} ({span})"


def seed_ranges(seeds: list[int]) -> str:
    """``0, 1``, ``0 .. 47565`` or ``0 .. 3, 7, 9 .. 11``: seeds in runs, readable for any
    count (three or more in a row are a range)."""
    runs: list[list[int]] = []
    for seed in seeds:
        if runs and seed == runs[-1][-1] + 1:
            runs[-1].append(seed)
        else:
            runs.append([seed])
    parts = [f"{run[0]} .. {run[-1]}" if len(run) > 2 else ", ".join(map(str, run)) for run in runs]
    return ", ".join(parts)


def leave_out_unfinished_seed(outcome: ExperimentResult) -> None:
    """When the first seed ran every step, drop the later seeds that stopped before (Ctrl-C in
    their pass, or their simulation failed): averaged with whole seeds, an R_hat_T over fewer
    steps would pass for one like theirs. The run stays partial and says which seed is left
    out."""
    results = outcome.results
    if not results:  # stopped before any seed started
        return
    whole = results[0].completed_steps
    if results[0].error:  # the first seed stopped too (seeds run at once): all kept
        return
    while len(results) > 1 and results[-1].completed_steps < whole:
        outcome.left_out = results.pop()
        if len(outcome.traffic) > len(results):
            outcome.traffic.pop()
        if len(outcome.sources) > len(results):
            outcome.sources.pop().close()


def limit_threads(n: int = 1) -> None:
    """Run the numeric libraries on ``n`` threads: the commands that run swarms call this.

    A swarm's Q-network infers on a handful of rows, where one thread is fastest and leaves
    the other core to the traffic simulation (several threads oversubscribe a 2-core machine:
    10x slower).
    Set before torch is imported it is torch's default; set after, it is applied directly.
    """
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, str(n))
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(n)


def comma_names(text: str, flag: str) -> list[str]:
    """The names of a comma-separated flag, blanks around each dropped (none: the flag names
    nothing); an empty name between names (``a,,b``, ``a,``) is refused naming the flag."""
    names = [s.strip() for s in text.split(",")]
    if not any(names):
        return []
    if "" in names:
        raise UserError(
            f"{flag} {text!r}: name {names.index('') + 1} of {len(names)} is empty (two commas "
            "in a row, or one at an end); separate the names by single commas, e.g. random,greedy"
        )
    return names


def parse_swarm_names(text: str | None, default: Sequence[str], flag: str = "--swarms"):
    """Swarm names from a comma-separated flag (or ``default``), checked against the registry."""
    names = comma_names(text, flag) if text is not None else list(default)
    if not names:
        raise UserError(f"{flag} is empty; name at least one swarm")
    for name in names:
        try:
            check_swarm_name(name)
        except UserError as exc:
            raise UserError(f"{flag}: {exc}") from None
    if len(set(names)) != len(names):
        raise UserError(f"{flag}: a swarm is listed twice")
    return names


def is_live(experiment: Experiment) -> bool:
    """Whether the experiment's traffic is simulated once per seed (not a tape, a live kind)."""
    return experiment.tape is None and is_live_kind(experiment.config.traffic.kind)


def build_source(experiment: Experiment, index: int = 0) -> TrafficSource:
    """The traffic of the ``index``-th seed: a replayed tape, or the config's own traffic."""
    config = experiment.config
    if experiment.tape is not None:
        from twin.traffic.tape import TapeTraffic

        return TapeTraffic.from_file(experiment.tape, config)
    source = build_traffic(
        config,
        index,
        experiment.traffic_seed,
        experiment.separate_process,  # the simulation works ahead on the other core
        **experiment.traffic_options,
    )
    if experiment.outputs_dir is not None and hasattr(source, "output_dir"):
        seed = list(experiment.seeds)[index]
        source.output_dir = Path(experiment.outputs_dir) / (f"seed-{seed}" if index else "")
    return source


def build_swarms(experiment: Experiment) -> dict[str, Policy]:
    """The experiment's swarms, each with the config's options overlaid by the experiment's."""
    config = experiment.config
    swarms = {}
    for name in experiment.swarms:
        try:
            swarms[name] = config.make_swarm(name, **experiment.swarm_options.get(name, {}))
        except Exception as exc:  # a missing checkpoint or torch: skip a learned swarm if allowed
            if not (experiment.skip_unavailable and is_learned(name)):
                raise
            notify(f"twin: notice: swarm {name!r} skipped ({exc})")
    if not swarms:
        raise UserError("no swarm to run; give --swarms random,greedy,sweeping")
    return swarms


def check_swarm_outages(
    config: ScenarioConfig,
    swarms: dict[str, Policy],
    horizon: int,
    overrides: dict[str, dict] | None = None,
    overrides_file: Path | None = None,
) -> None:
    """Each swarm's own coordinator outages end by the horizon (:func:`check_outages`), named
    where they are given: ``overrides_file`` when ``overrides`` (a sweep's or a flag's options,
    by swarm) give them, else the config when its ``[swarm_options]`` do."""
    from twin.patrol import check_outages

    for name, policy in swarms.items():
        try:
            check_outages(name, policy, horizon)
        except UserError as exc:
            if "outages" in (overrides or {}).get(name, {}):
                if overrides_file is None:
                    raise
                raise UserError(f"{overrides_file}: {exc}") from None
            if "outages" in config.swarm_options.get(name, {}):
                raise UserError(f"{config.path}: {exc}") from None
            raise


def check_swarm_histories(swarms: dict[str, Policy], source: TrafficSource) -> None:
    """Each swarm's own history of earlier days (``[swarm_options.<swarm>].history``) is one
    of this traffic's grid, horizon and clock, and holds none of its days, as ``--history``
    is (:func:`twin.belief.check_source`)."""
    from twin.belief import check_source

    for name, policy in swarms.items():
        history = getattr(policy, "history", None)
        if history is not None:
            check_source(history, history.path or f"[swarm_options.{name}].history", source)


@contextlib.contextmanager
def stop_on_interrupt(
    enabled: bool = True,
    on_stop: Callable[[], None] | None = None,
    doing: str = "stopping after the current step and writing a partial run",
) -> Iterator[Callable[[], bool]]:
    """Within the block, a first Ctrl-C (SIGINT) or SIGTERM only sets a flag (the yielded
    callable turns true) so the run can stop after its current step and keep what it did, and
    calls ``on_stop()`` (which passes the word to worker processes) and says it is ``doing``
    so; a second one raises :class:`KeyboardInterrupt` at once. The previous handlers are
    restored on exit.

    Nothing is installed off the main thread, or for a signal whose handler is not the one
    that raises :class:`KeyboardInterrupt` (ignored, as SIGINT in a background job, or handled
    by the caller): the flag then stays false.
    """
    flag = threading.Event()
    at_once = {
        signal.SIGINT: signal.default_int_handler,
        signal.SIGTERM: interrupt_on_terminate,  # twin's command boundary installs it
    }
    usable = [
        signum
        for signum, handler in at_once.items()
        if enabled
        and threading.current_thread() is threading.main_thread()
        and signal.getsignal(signum) is handler
    ]
    if not usable:
        yield flag.is_set
        return

    def first(signum, frame) -> None:
        flag.set()
        STOP_ASKED.set()
        for each in usable:  # the next one stops at once
            signal.signal(each, at_once[each])
        if on_stop is not None:
            on_stop()
        how = "interrupted" if signum == signal.SIGINT else "terminated"
        start = "\n" if sys.stderr.isatty() else ""  # off a progress bar's line
        print(f"{start}twin: {how}; {doing} (Ctrl-C again to stop at once)", file=sys.stderr)

    previous = {signum: signal.signal(signum, first) for signum in usable}
    try:
        yield flag.is_set
    finally:
        STOP_ASKED.clear()
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def run_experiment(
    experiment: Experiment,
    progress: bool = False,
    keep_sources: bool = False,
    on_source=None,
    interruptible: bool = False,
    on_step=None,
) -> ExperimentResult:
    """Run every seed of ``experiment``: one patrol pass of all swarms per seed.

    ``on_source(source)`` is called once per seed after the traffic source is built (the CLI
    prints what it is about to simulate). With ``keep_sources`` live sources stay open for
    :func:`twin.runs.record` (their MFD fit and tape); otherwise each is closed after its pass. With
    ``interruptible`` a Ctrl-C stops the run after its current step (:func:`stop_on_interrupt`):
    the result keeps the steps done, runs no more seeds and says ``interrupted``.
    ``on_step`` is handed to :func:`twin.patrol.run_patrol` (the GUI's per-step drawer).

    With ``experiment.workers`` > 1 the seeds run at once, each in a worker process
    (:func:`_run_seeds_in_workers`; ``on_source`` is then called as the seeds finish, in seed
    order, with the source the worker ran): the same results, in the same order, as one after
    another.
    """
    if parallel(experiment) and on_step is None:
        signal_file = StopFile()
        try:
            with stop_on_interrupt(interruptible, lambda: signal_file.request(-1)) as stop:
                outcome = _run_seeds_in_workers(
                    experiment, progress, keep_sources, on_source, stop, signal_file
                )
        finally:
            signal_file.remove()
    else:
        with stop_on_interrupt(interruptible) as stop:
            outcome = _run_seeds(experiment, progress, keep_sources, on_source, stop, on_step)
    outcome.interrupted = stop() or any(
        (r.error or "").startswith(INTERRUPTED) for r in outcome.results
    )
    leave_out_unfinished_seed(outcome)
    say_empty_maps(outcome)
    return outcome


def say_empty_maps(outcome: ExperimentResult) -> None:
    """A notice for each seed whose maps are 0 in every cell from step 1 on: nothing to see,
    so every swarm scores alike (a window without demand, vehicles only on lanes the grid
    leaves out such as SUMO's racing game on vip-only lanes, disturbances that fade at once)."""
    from twin.boundary import notify

    for r in outcome.results:
        maps = r.importance
        if maps is not None and len(maps) > 1 and not np.any(maps[1:]):
            notify(
                f"twin: notice: seed {r.seed}: the importance is 0 in every cell from step 1 on: "
                "the swarms have nothing to see, so every swarm scores alike (a SUMO window "
                "without demand, or with vehicles only on lanes the grid leaves out; synthetic "
                "disturbances that fade within a step)"
            )


def parallel(experiment: Experiment) -> bool:
    """Whether the experiment's seeds run in worker processes: more than one seed and more than
    one worker. Each worker builds its seed's traffic: a live simulation of its own, or the
    synthetic or replayed traffic every seed shares (built once per seed then)."""
    return experiment.workers > 1 and len(experiment.seeds) > 1


def _run_seeds(
    experiment, progress, keep_sources, on_source, stop, on_step=None
) -> ExperimentResult:
    t0 = time.perf_counter()
    results, traffic, sources = [], [], []
    policies: dict[str, dict[str, Any]] = {}
    live = is_live(experiment)
    if not live:
        check_memory(experiment, *planned_shape(experiment))
    shared_source = None if live else build_source(experiment)
    for n, seed in enumerate(experiment.seeds):
        source = shared_source or build_source(experiment, n)
        try:
            result, meta, policies = _run_seed(
                experiment, n, seed, source, stop, progress, on_source, on_step
            )
            results.append(result)
            traffic.append(meta)
        finally:
            if keep_sources:
                sources.append(source)
            elif source is not shared_source:
                source.close()
        if result.error or stop():  # a live run failed or Ctrl-C: keep what was done, stop
            break
    if shared_source is not None and not keep_sources:
        shared_source.close()
    return ExperimentResult(
        experiment, results, traffic, policies, time.perf_counter() - t0, sources
    )


def _run_seed(experiment, n, seed, source, stop, progress=False, on_source=None, on_step=None):
    """One seed's patrol pass of all swarms over ``source``: its result, the source's metadata
    and what each swarm says of itself. A live run's memory is checked on its first seed, once
    its grid is known."""
    if is_live(experiment) and n == 0:
        check_memory(experiment, source.grid.shape, source.horizon, source)
    check_swarm_fits(experiment.config, source.grid)
    config = experiment.config
    check_faults(config, config.swarm.n_drones, source.horizon)
    if on_source is not None:
        on_source(source)
    swarms = build_swarms(experiment)
    check_swarm_outages(config, swarms, source.horizon, experiment.swarm_options)
    check_swarm_histories(swarms, source)
    faults = config.fault_plan()
    twins = build_swarms(experiment) if faults is not None and config.faults.compare else None
    sighting = source.sighting_model()  # how the drones' sightings are made: a filter's noise
    for policy in [*swarms.values(), *(twins or {}).values()]:
        if hasattr(policy, "use_sighting_model"):
            policy.use_sighting_model(sighting)
    starts = start_positions(experiment.config, source.grid, np.random.default_rng(seed))
    result = run_patrol(
        source,
        swarms,
        starts,
        experiment.config.params,
        seed,
        progress=progress,
        keep_importance=experiment.keep_importance,
        stop=stop,
        on_step=on_step,
        faults=faults,
        fault_free=twins,
    )
    result.extra["sighting"] = sighting  # the belief models' measurement variance
    detectors = source.detector_observations()
    if detectors is not None:
        result.extra["detectors"] = detectors  # a belief model's observations
    incidents = source.incidents_info()
    if incidents:
        result.extra["incidents"] = incidents  # scored by monitoring
        if result.fault_free is not None:
            result.fault_free.extra["incidents"] = incidents
    policies = {name: p.describe() for name, p in swarms.items() if hasattr(p, "describe")}
    return result, source.metadata(), policies


class StopFile:
    """The word to stop, passed from the parent to the workers of a parallel run: a file in a
    fresh temporary folder that holds an index; every seed above it stops after its current
    step (or does not start). ``-1``: every seed (Ctrl-C); ``n``: the seeds after seed n (seed
    n failed: the seeds one after another would have stopped there)."""

    def __init__(self) -> None:
        import tempfile

        from twin.resources import scratch_dir

        self.folder = Path(tempfile.mkdtemp(prefix="twin-stop-", dir=scratch_dir()))
        self.path = self.folder / "stop"

    def request(self, after: int) -> None:
        current = self.read()
        if current is not None and current <= after:
            return
        tmp = self.folder / f"stop.{after + 1}.tmp"
        tmp.write_text(str(after))
        os.replace(tmp, self.path)  # never seen half-written

    def read(self) -> int | None:
        return read_stop(self.path)

    def remove(self) -> None:
        import shutil

        shutil.rmtree(self.folder, ignore_errors=True)


def read_stop(path: Path) -> int | None:
    """The index in a :class:`StopFile`'s file, or None while no stop was asked for."""
    try:
        return int(Path(path).read_text())
    except (OSError, ValueError):
        return None


@dataclass
class SeedOutcome:
    """What a worker sends back of one seed (:func:`run_seed_in_worker`)."""

    index: int
    result: PatrolResult
    traffic: dict[str, Any]
    policies: dict[str, dict[str, Any]]
    source: TrafficSource | None  # the source as the run left it, when the caller keeps sources
    notices: list[str] = field(default_factory=list)  # said in the worker, said here in order


def run_seed_in_worker(
    experiment: Experiment, index: int, stop_path: str, keep_source: bool
) -> SeedOutcome | None:
    """One seed of a parallel run, in a worker process: build its simulation, run the swarms
    over it and send back the result (with the source, for the run folder's files). None: a
    stop was asked for before the seed started."""
    limit_threads()
    path = Path(stop_path)
    stopped = [False]

    def stop() -> bool:  # one stat per step; the word, once read, holds
        if not stopped[0] and path.exists():
            after = read_stop(path)
            stopped[0] = after is not None and index > after
        return stopped[0]

    if stop():
        return None
    seed = list(experiment.seeds)[index]
    # the seed's notices go back with its outcome and are said by the parent (once per
    # command); a seed that fails is its error alone, as without workers
    count_said(False)
    drop_notices()
    hold_notices(to_end=True)
    try:
        source = build_source(experiment, index)
        try:
            result, traffic, policies = _run_seed(experiment, index, seed, source, stop)
        finally:
            source.close()
    finally:
        notices = drop_notices()
    kept = source if keep_source else None
    return SeedOutcome(index, result, traffic, policies, kept, notices)


def _run_seeds_in_workers(
    experiment, progress, keep_sources, on_source, stop, signal_file: StopFile
) -> ExperimentResult:
    """The seeds of an experiment on ``experiment.workers`` worker processes (a local process
    pool, or Ray), each seed its traffic (a live simulation) with its swarms; results in seed
    order.

    A seed that fails mid-run (its result says why) stops the seeds after it, which are then
    left out: the same seeds and results as one after another. An error (bad input, a bug)
    stops every worker at once and is raised here. Ctrl-C stops every seed after its current
    step and keeps the seeds that ran the most steps (every step, or the longest partial run);
    the others are left out (``left_out_seeds``): no table compares seeds of unequal lengths.
    """
    from twin.executors import EXECUTORS, local_tasks, ray_tasks

    if experiment.executor not in EXECUTORS:
        raise UserError(f"--executor {experiment.executor!r}: choose from {', '.join(EXECUTORS)}")
    t0 = time.perf_counter()
    seeds = list(experiment.seeds)
    workers = min(experiment.workers, len(seeds))
    if not is_live(experiment):
        check_memory(experiment, *planned_shape(experiment))
    else:  # the grid is known only in the workers: at least a simulation each, up front
        check_workers_fit(experiment.workers, workers, max_memory_gb(experiment))
    tasks = [(experiment, n, str(signal_file.path), keep_sources) for n in range(len(seeds))]
    if experiment.executor == "ray":
        outcomes = ray_tasks(run_seed_in_worker, tasks, workers)
    else:
        outcomes = local_tasks(
            run_seed_in_worker, tasks, workers, ignore_sigint=True, kill_on_close=True
        )
    done: dict[int, SeedOutcome | None] = {}
    announced = 0  # on_source goes through the seeds in order, as each is done

    def announce(upto: int) -> None:
        nonlocal announced
        while announced < upto and announced in done:
            value = done[announced]
            if on_source is not None and value is not None and value.source is not None:
                release_notices()  # a seed ran: its simulation started
                on_source(value.source)
            announced += 1

    bar = _seed_bar(len(seeds), progress)
    try:
        for n, value, error in outcomes:
            if error is not None:
                signal_file.request(-1)
                raise _worker_error(error, seeds[n])
            if bar is not None:
                bar.update(1)
            for line in value.notices if value is not None else []:
                notify(line)
            done[n] = value  # None: stopped before it started
            if value is not None and value.result.error and not stop():
                signal_file.request(n)  # the seeds after a failed one stop
            announce(len(seeds))
    finally:
        outcomes.close()  # an early end kills the workers still running
        if bar is not None:
            bar.close()
    kept = sorted(n for n, value in done.items() if value is not None)
    left_out: list[int] = []
    if not stop():
        failed = [n for n in kept if done[n].result.error]
        if failed:
            kept = [n for n in kept if n <= failed[0]]
    else:  # stopped at once, each seed after its current step
        kept, left_out = longest_seeds({n: done[n].result.completed_steps for n in kept})
        for n in left_out:
            if done[n].source is not None:
                done[n].source.close()
    kept_outcomes = [done[n] for n in kept]
    for n in kept:  # those after a seed that never started
        if n >= announced and on_source is not None and done[n].source is not None:
            release_notices()
            on_source(done[n].source)
    outcome = ExperimentResult(
        experiment,
        [o.result for o in kept_outcomes],
        [o.traffic for o in kept_outcomes],
        kept_outcomes[-1].policies if kept_outcomes else {},
        time.perf_counter() - t0,
        [o.source for o in kept_outcomes if o.source is not None],
    )
    if left_out:
        outcome.left_out = done[left_out[-1]].result
        outcome.left_out_seeds = {seeds[n]: done[n].result.completed_steps for n in left_out}
    return outcome


def longest_seeds(steps: dict[int, int]) -> tuple[list[int], list[int]]:
    """The seeds (by index) that ran the most steps, and the others: seeds stopped at once by
    Ctrl-C, each after its current step, are kept only as long as the longest, so that no
    table averages or pairs an R_hat_T over fewer steps with longer ones."""
    longest = max(steps.values(), default=0)
    kept = sorted(n for n, done in steps.items() if done == longest)
    return kept, sorted(n for n in steps if n not in kept)


def _worker_error(error: BaseException, seed: int) -> BaseException:
    """A worker's exception as raised here: bad input as it is; a worker that died as one line
    (:class:`UserError`); anything else as it is (its traceback goes to ``error.log``)."""
    from concurrent.futures.process import BrokenProcessPool

    if isinstance(error, BrokenProcessPool):
        return UserError(
            f"the worker process of seed {seed} died ({error}); nothing was written, rerun "
            "with fewer --workers (memory) or --workers 1"
        )
    return error


def _seed_bar(total: int, enabled: bool):
    """One progress bar over the seeds of a parallel run (each worker's own bar is off)."""
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="seeds", unit="seed", leave=False, dynamic_ncols=True)


DEFAULT_MAX_MEMORY_GB = 8.0
MEMORY_ENV = "TWIN_MAX_MEMORY_GB"


def max_memory_gb(experiment: Experiment) -> float:
    """The memory limit: the experiment's (``--max-memory-gb``), else ``$TWIN_MAX_MEMORY_GB``,
    else 8 GB."""
    return memory_limit_gb(experiment.max_memory_gb)


def check_workers_fit(
    given: int, workers: int, limit: float, what: str = "live simulations"
) -> None:
    """``workers`` processes at once (``--workers given``) fit the memory ``limit`` (GB) at
    :data:`WORKER_BYTES` each, at least (an interpreter and a simulator); else one line."""
    if limit * 1e9 < WORKER_BYTES:  # not even one fits: fewer workers is no fix
        raise UserError(
            f"--workers {given}: one of the {what} needs at least {_gb(WORKER_BYTES)} GB (an "
            f"interpreter and its simulator), over the {limit:g} GB limit; raise "
            f"--max-memory-gb (or ${MEMORY_ENV}) to at least {_gb(WORKER_BYTES)}"
        )
    if workers * WORKER_BYTES > limit * 1e9:
        raise UserError(
            f"--workers {given}: {workers} {what} at once need at least "
            f"{_gb(workers * WORKER_BYTES)} GB ({_gb(WORKER_BYTES)} GB each), over the {limit:g} "
            f"GB limit; use at most {max(1, int(limit * 1e9 // WORKER_BYTES))} --workers (this "
            f"machine has {os.cpu_count()} CPUs), or raise --max-memory-gb"
        )


def memory_limit_gb(value: float | None = None) -> float:
    """The memory limit in GB: ``value`` (``--max-memory-gb``), else ``$TWIN_MAX_MEMORY_GB``,
    else 8 GB; a limit that is not a number > 0 is refused in one line."""
    where = "--max-memory-gb"
    if value is None:
        where = MEMORY_ENV
        text = os.environ.get(MEMORY_ENV, "").strip()
        if not text:
            return DEFAULT_MAX_MEMORY_GB
        try:
            value = float(text)
        except ValueError:
            raise UserError(
                f"{where} = {text!r} is not a number; give the limit in GB, e.g. 8"
            ) from None
    if not np.isfinite(value) or value <= 0:
        raise UserError(f"{where} = {value}: not a number > 0; give the limit in GB, e.g. 8")
    return float(value)


def planned_shape(experiment: Experiment) -> tuple[tuple[int, int] | None, int | None]:
    """Grid shape and horizon of a synthetic or replayed run, read cheaply (the config, or the
    tape's footer); ``(None, None)`` when unknown (a broken tape: its reader will say why)."""
    if experiment.tape is not None:
        from twin.traffic.tape import tape_footer

        meta = tape_footer(experiment.tape) or {}
        nx, ny, horizon = meta.get("nx"), meta.get("ny"), meta.get("horizon")
        if not all(
            isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in (nx, ny, horizon)
        ):
            return None, None  # the tape reader gives the one-line error
        return (nx, ny), horizon
    config = experiment.config
    return (config.grid.nx, config.grid.ny), int(config.traffic.horizon)


#: Bytes per swarm and step of a seed's series and trajectory rows, and per seed of its
#: result's objects (:func:`estimate_memory`).
SERIES_BYTES, SEED_BYTES = 600, 60_000


def estimate_memory(
    experiment: Experiment,
    shape: tuple[int, int],
    horizon: int,
    warmup_steps: int = 0,
    live: bool = False,
) -> float:
    """Bytes a run needs, roughly and from above, before anything heavy is allocated.

    Per cell and step: every seed's result keeps its importance maps and recorded truth
    (float32, ``(T+1) x nx x ny`` each: 8 B); monitoring's event search ~12 B while one seed is
    scored; synthetic traffic precomputes its maps (float64, stacked: 16 B); live traffic keeps
    each seed's snapshots (int32 counts + float32 speeds, warm-up included: 8 B), stacks them
    into one seed's tape at a time as it is written (8 B more) and writes it as a long table
    (~48 B). Per cell and swarm: its state, view and belief map (~64 B). Per
    swarm, drone and step: positions (16 B per seed). Per swarm and step of each seed: its
    series and trajectory rows as gathered into the run's tables (600 B); per seed: its
    result's objects (60 KB); from peak memory (`/usr/bin/time`) on a 10 x 12 grid, T = 60,
    1500 and 3000 seeds of 1 swarm and 3000 of 3 (122 to 133 and 179 KB per seed; the terms
    above gave 67), with a margin of about a fifth. Beside them: this process's interpreter
    and, for a live run, its simulator (:data:`PROCESS_BYTES`, :data:`SIMULATOR_BYTES`; 4 m
    cells of 1 s steps with a 15-minute warm-up of 898 snapshots, T = 1: 1.37 GB peak in this
    process, 0.22 in the simulator's, against 1.72 estimated). With
    ``[faults]``, each swarm's fault-free twin counts as one more swarm.

    Seeds run at once on W workers (:func:`parallel`): each worker holds one simulation with its
    swarms (:data:`WORKER_BYTES`: an interpreter and the traffic simulator's process), its
    seed's result and tape while it runs, and the copy it sends back (twice those 8 + 8 B per
    cell and step), beside the parent, which gathers every seed's.
    """
    cells = shape[0] * shape[1]
    steps = horizon + 1
    n_seeds, n_swarms = len(experiment.seeds), len(experiment.swarms)
    config = experiment.config
    if config.fault_plan() is not None and config.faults.compare:
        n_swarms *= 2  # each swarm's fault-free twin runs beside it
    per_cell_step = 8 * n_seeds + 12
    if live:
        per_cell_step += (8 * n_seeds + 8) * (steps + warmup_steps) / steps + 48
    elif experiment.tape is None and experiment.config.traffic.kind == "synthetic":
        per_cell_step += 16
    else:  # a tape: its counts, speeds (and the table they are read from, ~40 B)
        per_cell_step += 48
    n_drones = min(experiment.config.swarm.n_drones, cells)  # more cannot fit: refused later
    need = (
        PROCESS_BYTES
        + (SIMULATOR_BYTES if live else 0.0)
        + cells * steps * per_cell_step
        + cells * n_swarms * 64
        + n_swarms * n_seeds * steps * (n_drones * 16 + SERIES_BYTES)
        + n_seeds * SEED_BYTES
    )
    workers = n_workers(experiment)
    if workers > 1:
        per_worker = (
            WORKER_BYTES
            + cells * steps * 2 * (8 + 8 * (steps + warmup_steps) / steps)
            + cells * n_swarms * 64
            + n_swarms * steps * n_drones * 16 * 2
        )
        need += workers * per_worker
    return float(need)


#: A Python interpreter with twin's modules and its libraries (0.22 GB peak for `twin
#: evaluate --config synthetic --swarms random`, 0.42 GB with torch for `--swarms rl`), and a
#: live traffic simulation in its own process (about 0.4 GB on the default scenario).
PROCESS_BYTES = SIMULATOR_BYTES = 0.4e9

#: A worker of a parallel run beside its parent: an interpreter and one live simulation
#: (peak resident memory on the default scenario: about 0.4 GB for the runner plus 0.4 GB for
#: the simulator; docs/benchmarks.md).
WORKER_BYTES = PROCESS_BYTES + SIMULATOR_BYTES


def n_workers(experiment: Experiment) -> int:
    """The worker processes a run uses at once: ``experiment.workers`` up to the number of seeds
    when its seeds run in parallel (:func:`parallel`), else 0 (all in this process)."""
    if not parallel(experiment):
        return 0
    return min(experiment.workers, len(experiment.seeds))


def check_resources(
    experiment: Experiment,
    out: Path,
    flag: str = "--out",
    owner: Callable[[Path], None] | None = None,
) -> None:
    """Before any folder is made: the memory estimate of a run whose grid is known from its
    config or tape (:func:`check_memory`), or a live run's scratch folder in the cache
    (:func:`twin.resources.scratch_dir`), then the output folder (:func:`disk_estimate_mb`;
    :func:`twin.outputs.check_output_dir`)."""
    from twin.outputs import check_output_dir

    max_memory_gb(experiment)  # a bad limit is refused first
    if not is_live(experiment):
        check_memory(experiment, *planned_shape(experiment))
    else:  # a live simulation keeps its messages in the cache's scratch folder
        from twin.resources import scratch_dir

        scratch_dir()
    check_output_dir(out, flag, disk_estimate_mb(experiment), owner=owner)


def disk_estimate_mb(experiment: Experiment) -> float:
    """Disk space a run folder needs (MB), roughly and from above: the trajectories and series
    (~100 B per swarm, seed, step and drone), the first seed's importance maps (float32), and a
    live run's tapes (~8 B per cell and step and seed); at least
    :data:`twin.outputs.MIN_FREE_MB`. A live run's grid is not known before the simulation's
    network is read: the config's explicit grid is used when it gives one."""
    from twin.outputs import MIN_FREE_MB

    shape, horizon = planned_shape(experiment)
    if shape is None or horizon is None:
        try:
            shape = experiment.config.explicit_shape()
            horizon = experiment.config.traffic.horizon
        except Exception:  # a live scenario's grid comes from its network
            return float(MIN_FREE_MB)
    if shape is None or not horizon:
        return float(MIN_FREE_MB)
    cells, steps = shape[0] * shape[1], int(horizon) + 1
    n_seeds, n_swarms = len(experiment.seeds), max(len(experiment.swarms), 1)
    drones = min(experiment.config.swarm.n_drones, cells)  # more cannot fit: refused later
    size = n_seeds * n_swarms * steps * (drones * 100 + 200) + cells * steps * 4
    if is_live(experiment):
        size += cells * steps * 8 * n_seeds
    return max(float(MIN_FREE_MB), size / 1e6 * 1.2)


def check_memory(
    experiment: Experiment,
    shape: tuple[int, int] | None,
    horizon: int | None,
    source: TrafficSource | None = None,
) -> None:
    """Refuse (one line, with the estimate and a hint) a run past the memory limit."""
    if shape is None or horizon is None:
        return
    from twin.resources import check_grid_size

    where = str(experiment.tape or experiment.config.path)
    check_grid_size(*shape, where, "use a coarser grid")
    if horizon > 10**9:
        raise UserError(f"{where}: horizon {horizon} is not a number of steps twin can run")
    limit = max_memory_gb(experiment)
    warmup = int(source.warmup_steps()) if source is not None else 0
    live = source is not None and source.live
    need = estimate_memory(experiment, shape, horizon, warmup, live=live)
    if need <= limit * 1e9:
        return
    workers = n_workers(experiment)
    if workers > 1:  # the workers themselves past the limit: only fewer of them can help
        check_workers_fit(experiment.workers, workers, limit, "worker processes")
    floor = estimate_memory(experiment, (1, 1), 1, 0, live=live)
    if floor > limit * 1e9:  # no grid or horizon fits: only the limit (or workers) can change
        on, fewer = (
            (f" on {workers} workers", "use fewer --workers or ") if workers > 1 else ("", "")
        )
        at_once = max(workers, 1)  # fewer seeds than workers would only be fewer workers
        fit = 0
        if len(experiment.seeds) > at_once:
            fit = _seeds_that_fit(experiment, limit, shape, horizon, warmup, live)
        if fit >= at_once:  # the seeds themselves are what is past the limit
            raise UserError(
                f"{len(experiment.seeds)} seeds need about {_gb(floor)} GB even on 1 x 1 cells "
                f"and 1 step{on}, over the --max-memory-gb / ${MEMORY_ENV} = {limit:g} GB limit; "
                f"give at most {fit} --seeds ({shape[0]} x {shape[1]} cells x {horizon} steps)"
                f"{', fewer --workers' if workers > 1 else ''}, or raise the limit"
            )
        raise UserError(
            f"--max-memory-gb / ${MEMORY_ENV} = {limit:g} GB is below what this run takes on "
            f"any grid{on} (about {_gb(floor)} GB on 1 x 1 cells and 1 step); {fewer}raise it"
        )
    ratio = (need / (limit * 1e9)) ** 0.5
    hint = source.coarser_hint(ratio) if source is not None else None
    if hint is None:
        hint = f"a grid about {ratio:.1f} times coarser per side, fewer steps or fewer seeds"
    on = f" on {workers} workers" if workers > 1 else ""
    fewer = ", fewer --workers" if workers > 1 else ""
    raise UserError(
        f"{shape[0]} x {shape[1]} cells x {horizon} steps x {len(experiment.swarms)} swarms x "
        f"{len(experiment.seeds)} seeds{on} need about {_gb(need)} GB, over the "
        f"{limit:g} GB limit; use {hint}{fewer}, or raise --max-memory-gb / ${MEMORY_ENV}"
    )


def _seeds_that_fit(
    experiment: Experiment,
    limit: float,
    shape: tuple[int, int],
    horizon: int,
    warmup: int,
    live: bool,
) -> int:
    """The most of the experiment's seeds (its first ones) that fit the limit on this grid and
    horizon, on its workers (0: not one): the estimate grows with the seeds."""
    seeds = list(experiment.seeds)

    def fits(n: int) -> bool:
        need = estimate_memory(replace(experiment, seeds=seeds[:n]), shape, horizon, warmup,
                               live=live)  # fmt: skip
        return need <= limit * 1e9

    low, high = 0, len(seeds)  # fits(low) holds (no seed), fits(high) is what is asked
    while high - low > 1:
        mid = (low + high) // 2
        low, high = (mid, high) if fits(mid) else (low, mid)
    return high if fits(high) else low


def _gb(n_bytes: float) -> str:
    """Bytes as GB with one decimal rounded up (an estimate over a limit never reads as at
    or below it), or two significant digits below 0.1 GB."""
    gb = n_bytes / 1e9
    return f"{math.ceil(round(gb * 10, 6)) / 10:.1f}" if gb >= 0.1 else f"{gb:.2g}"


def run_metadata(outcome: ExperimentResult, kind: str, **extra: Any) -> dict[str, Any]:
    """What ``run.json`` records about an experiment beside the results."""
    config = outcome.experiment.config
    return {
        "kind": kind,
        "config": str(config.path),
        "traffic": outcome.traffic[0] if outcome.traffic else None,
        **({"traffic_by_seed": outcome.traffic} if len(outcome.traffic) > 1 else {}),
        "params": vars(config.params),
        "n_drones": config.swarm.n_drones,
        "starts": config.swarm.starts,  # "random" (each seed's draw) or the cells
        "wall_seconds": round(outcome.seconds, 3),
        "partial": outcome.partial,
        **({"partial_reason": outcome.partial_reason()} if outcome.left_out else {}),
        "policies": outcome.policies,
        **extra,
    }


def close_sources(outcome: ExperimentResult) -> None:
    for source in outcome.sources:
        source.close()
    outcome.sources.clear()

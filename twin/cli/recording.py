"""What ``twin run`` and ``twin evaluate`` share: their flags applied to the scenario config,
and one run-and-record (check resources -> prepare the run folder -> run the experiment ->
record it -> print its tables -> render its report)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.config import ScenarioConfig, with_overrides
from twin.errors import UserError
from twin.experiment import (
    Experiment,
    ExperimentResult,
    check_resources,
    run_experiment,
    run_metadata,
    stop_on_interrupt,
)
from twin.runs import (
    check_holds_a_run,
    discard_run_dir,
    invocation,
    new_run_dir,
    prepare_run_dir,
    record,
)

BELIEF_FILE = "belief_models.csv"
BELIEF_MAPS_FILE = "belief_maps.npz"


def with_flags(config: ScenarioConfig, flags: Mapping[str, tuple[str, Any]]) -> ScenarioConfig:
    """``config`` with the flags given (``{"--drones": ("swarm.n_drones", args.drones)}``; a
    value of None: not given) applied as dotted overrides (:func:`twin.config.with_overrides`):
    every value is validated by the config's models, and an error names the flag."""
    given = {flag: (key, value) for flag, (key, value) in flags.items() if value is not None}
    overrides = {key: value for key, value in given.values()}
    return with_overrides(config, overrides, {key: flag for flag, (key, _) in given.items()})


@dataclass
class Recorded:
    """A finished run, written to its run folder."""

    run_dir: Path
    outcome: ExperimentResult
    summary: Any  # the summary table (pandas)
    comparison: Any  # each learned swarm against the best classical one (pandas; may be empty)
    beliefs: Any  # belief_models.csv's table, or None without --history


def run_and_record(
    command: str,
    args,
    experiment: Experiment,
    history=None,
    on_source: Callable | None = None,
    extra_meta: Callable[[ExperimentResult], dict[str, Any]] | None = None,
    outputs_folder: str | None = None,
    around: contextlib.AbstractContextManager | None = None,
    **run_options: Any,
) -> Recorded:
    """Run ``experiment`` for ``twin <command>`` and write its run folder (``args.out``, else
    ``runs/<command>-<time>``): resources checked before any folder is made, a refusal while
    it runs discards the folder; ``args.ceiling`` adds the ceiling rows unless interrupted,
    ``history`` the belief models (and goes to the swarms that plan on one). ``outputs_folder``: where in the run folder a live source
    writes its scenario's configured outputs; ``around`` is entered while the experiment runs
    (a display); ``run_options`` go to :func:`twin.experiment.run_experiment`."""
    if history is not None:
        hand_history(experiment, history)
    check_resources(  # before any folder is made; a given --out holds no user's files
        experiment, args.out or Path("runs"), owner=check_holds_a_run if args.out else None
    )
    if not getattr(args, "no_report", True):
        from twin.resources import check_cache

        check_cache("the report's figures keep their font cache there")
    run_dir = prepare_run_dir(args.out or new_run_dir("runs", command), invocation(command, args))
    if outputs_folder is not None:
        experiment.outputs_dir = run_dir / outputs_folder
    try:
        with around if around is not None else contextlib.nullcontext():
            outcome = run_experiment(
                experiment,
                progress=not args.quiet and sys.stderr.isatty(),
                interruptible=True,
                on_source=on_source,
                **run_options,
            )
    except UserError:
        discard_run_dir(run_dir)
        raise
    if not outcome.results:  # stopped (Ctrl-C, SIGTERM) before any seed started: nothing to keep
        discard_run_dir(run_dir)
        raise KeyboardInterrupt
    # a Ctrl-C while the finished run is written lets it finish (then stops the command): the
    # run's results are not thrown away for a folder half written
    with stop_on_interrupt(doing="finishing the run folder first") as stopped:
        meta = run_metadata(outcome, command, **(extra_meta(outcome) if extra_meta else {}))
        if history is not None and getattr(args, "history", None) is not None:
            meta["history"] = history_record(Path(args.history))  # its beliefs are replayed
        beliefs = belief_models(outcome, history, meta)
        maps = None
        if beliefs is not None:
            from twin.belief import belief_maps

            maps = belief_maps(outcome.results[0], history)
        summary, comparison = record(
            run_dir,
            outcome,
            meta,
            ceilings=args.ceiling and not outcome.interrupted,
            more_files=belief_writer(beliefs, maps),
        )
    if stopped():
        raise KeyboardInterrupt
    return Recorded(run_dir, outcome, summary, comparison, beliefs)


def history_record(path: Path) -> dict[str, str]:
    """run.json's ``history``: the file the belief models were scored with and its sha256, by
    which ``twin report`` finds it again to replay them (:mod:`twin.report.beliefs`)."""
    from twin.files import file_sha256

    return {"path": str(path.resolve()), "sha256": file_sha256(path)}


def hand_history(experiment: Experiment, history) -> None:
    """Give the run's history (``--history``) to every swarm that plans on one, over what its
    ``[swarm_options]`` say, and to every learned swarm (read when its checkpoint's state is
    the nowcast)."""
    from twin.notices import notify
    from twin.swarms import SWARMS, base_name, needs_history

    options = dict(experiment.swarm_options)
    for name in experiment.swarms:
        kind = SWARMS.get(base_name(name))
        if needs_history(name) or (kind is not None and kind.learned):
            own = {  # the swarm's own: the config's [swarm_options], the experiment's on top
                **experiment.config.swarm_options.get(name, {}),
                **options.get(name, {}),
            }.get("history")
            if own is not None and not _same_history(own, history, experiment.config.path):
                notify(
                    f"twin: notice: --history {getattr(history, 'path', None) or 'given'} replaces "
                    f"[swarm_options.{name}].history = {str(own)!r} for the swarm {name}"
                )
            options[name] = {**options.get(name, {}), "history": history}
    experiment.swarm_options = options


def _same_history(own, history, config_path: Path) -> bool:
    """Whether a swarm's own history (a History, or its file relative to the config) is the
    run's ``history``."""
    if own is history:
        return True
    path = getattr(own, "path", None) if not isinstance(own, (str, Path)) else own
    if path is None or getattr(history, "path", None) is None:
        return False
    return (Path(config_path).parent / path).resolve() == Path(history.path).resolve()


def print_tables(recorded: Recorded, title: str) -> None:
    """The Table 2 analog and each learned swarm against the best classical one."""
    from twin.metrics import format_comparison, format_results

    print(format_results(recorded.summary, title))
    if not recorded.comparison.empty:
        print(format_comparison(recorded.comparison))


def render_report(run_dir: Path) -> None:
    """The HTML report of the run folder (skipped when the report's packages are missing)."""
    try:
        from twin.report import write_report
    except ImportError:
        return
    print(f"report: {write_report(run_dir)}")


def belief_models(outcome, history, meta):
    """``belief_models.csv``'s table of a finished run with ``--history`` (None without)."""
    if history is None or not outcome.results:
        return None
    from twin.belief import run_beliefs
    from twin.runs import step_seconds_of

    return run_beliefs(outcome.results, history, step_seconds_of(meta))


def belief_writer(beliefs, maps=None):
    """The ``more_files`` of :func:`twin.runs.record` writing ``belief_models.csv`` and, for
    the report, the first seed's ``belief_maps.npz`` (:func:`twin.belief.belief_maps`)."""
    if beliefs is None:
        return None
    import numpy as np

    from twin.files import atomic_write

    def save_maps(path: Path) -> None:
        with open(path, "wb") as fh:
            np.savez_compressed(fh, **maps)

    def write(folder: Path) -> None:
        atomic_write(folder / BELIEF_FILE, lambda p: beliefs.to_csv(p, index=False))
        if maps is not None:
            atomic_write(folder / BELIEF_MAPS_FILE, save_maps)

    return write


def print_beliefs(beliefs, path: Path | None, label: str) -> None:
    if beliefs is not None:
        from twin.belief import format_belief_table

        title = f"Belief models (history {path}, {label}): {BELIEF_FILE}"
        print(format_belief_table(beliefs, title))


def print_degradation(run_dir: Path) -> None:
    """The degradation table's headline when the run had ``[faults]``."""
    path = Path(run_dir) / "degradation.csv"
    if path.exists():
        import pandas as pd

        from twin.faults import format_degradation

        print(format_degradation(pd.read_csv(path)))

"""``twin run``: the Shenzhen case study (Sec. IV-B) live on SUMO, all swarms on ONE SUMO run.

Builds the default network if missing, advances SUMO in lockstep with the swarms (one step =
cell size / drone speed of simulated time), prints the Table 2 analog and writes the run folder,
with the SUMO extras: ``network.json``, ``mfd.json``, ``mfd_samples.parquet``, ``tape.parquet``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from twin.cli import (
    add_scoring_arguments,
    add_worker_arguments,
    check_count,
    check_seeds,
    path_arg,
)
from twin.errors import UserError

DEFAULT_CONFIG = "configs/shenzhen.toml"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "run",
        help="run the swarms on a live SUMO simulation (default: the Shenzhen-like rush hour)",
        description="Run every swarm side by side on one SUMO simulation advanced in lockstep "
        "(one step = cell size / drone speed of simulated time). Without arguments: the "
        "Shenzhen-like network, 07:00-10:00, 20 x 30 cells of 500 m, 4 drones, T = 144. "
        "Swap in a network with --net/--routes, --sumocfg or --osm; without routes twin "
        "generates a rush-hour demand with SUMO's randomTrips.py.",
    )
    p.add_argument(
        "--config", type=path_arg, default=None, help=f"scenario (default {DEFAULT_CONFIG})"
    )
    p.add_argument(
        "--net",
        type=path_arg,
        help="a SUMO network (.net.xml) instead of the config's or the --sumocfg's",
    )
    p.add_argument(
        "--routes",
        type=path_arg,
        action="append",
        help="route/trip file(s) for --net or instead of the --sumocfg's (repeatable)",
    )
    p.add_argument(
        "--sumocfg", type=path_arg, help="a SUMO configuration (.sumocfg): network + demand"
    )
    p.add_argument(
        "--osm", type=path_arg, help="an OpenStreetMap extract, converted with netconvert"
    )
    p.add_argument(
        "--additional",
        type=path_arg,
        action="append",
        help="a SUMO additional file (vehicle types, signal programs, detectors, polygons; "
        "repeatable), besides those of the sumocfg",
    )
    p.add_argument(
        "--horizon",
        type=int,
        help="number of steps T (default: the config's, or what fits the window of a network "
        "given as files)",
    )
    p.add_argument(
        "--begin",
        type=str,
        help='time of T^0, e.g. "07:00" (default: the config\'s, or the begin of the window of '
        "a network given as files plus the warm-up)",
    )
    p.add_argument("--cell-m", type=float, help="cell size in m (default from the config)")
    p.add_argument("--drones", type=int, help="number of drones (default from the config)")
    p.add_argument(
        "--drone-speed",
        type=float,
        help="drone speed in km/h (default from the config); one step = cell size / speed",
    )
    p.add_argument("--swarms", type=str, help="comma-separated swarms (default from the config)")
    p.add_argument("--seed", type=int, help="first seed of the drones' starts and swarms")
    p.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="number of seeds: one SUMO simulation each, SUMO seeds sumo-seed, sumo-seed+1, ...",
    )
    p.add_argument(
        "--sumo-seed", type=int, help="SUMO's seed of the first simulation (default [traffic].seed)"
    )
    add_worker_arguments(p)
    p.add_argument("--meso", action="store_true", help="SUMO's mesoscopic model (faster)")
    p.add_argument("--out", type=path_arg, help="run folder (default runs/run-<time>)")
    add_scoring_arguments(p)
    add_gui_arguments(p)
    p.set_defaults(func=main)


def add_gui_arguments(p, always: bool = False) -> None:
    """``--gui``, ``--gui-swarms``, ``--gui-shade``, ``--record`` (``twin run``, ``twin replay``);
    ``always``: the command always draws in sumo-gui (``--gui`` is taken, and changes nothing)."""
    p.add_argument(
        "--gui",
        action="store_true",
        help="(always on: a replay is drawn in sumo-gui; without a display twin starts Xvfb)"
        if always
        else "watch it in sumo-gui (through traci; same simulation, same results); without a "
        "display twin starts Xvfb (apt-get install xvfb)",
    )
    p.add_argument(
        "--gui-swarms",
        type=str,
        help="comma-separated swarms drawn in the GUI, or 'all' (default: the learned swarm, rl "
        "if in the run, else its first learned one, and the best classical one, chosen before "
        "any result: lookahead if in the run, else its first coordinated classical swarm "
        "(greedy-coordinated, visit-gain, tours), else its first classical one)",
    )
    p.add_argument(
        "--gui-shade",
        choices=["belief", "truth"],
        help="shade cells by the importance the first shown swarm believes (the default), or "
        "the true one",
    )
    p.add_argument(
        "--record",
        type=path_arg,
        help="save the GUI's view at every step as a video (FILE.mp4 or FILE.gif); implies --gui",
    )


def gui_drawer(args: argparse.Namespace, swarms, owned: tuple[Path, str] | None = None):
    """The per-step drawer of ``--gui`` (None without it), its settings checked (the
    ``--gui-*`` flags are checked without ``--gui`` too: a typo is refused, not ignored).
    ``owned``: the folder twin writes afresh and its words (``--out``'s, a run's report), in
    which ``--record`` is refused."""
    from twin.experiment import comma_names
    from twin.sumo.gui import GuiDrawer, GuiSettings, check_settings

    shown = comma_names(args.gui_swarms, "--gui-swarms") if args.gui_swarms else None
    if args.gui_swarms is not None and not shown:
        raise UserError(
            f"--gui-swarms {args.gui_swarms!r}: names no swarm; give comma-separated swarms of "
            "the run, or all"
        )
    twice = [name for n, name in enumerate(shown or []) if name in shown[:n]]
    if twice:
        raise UserError(
            f"--gui-swarms {args.gui_swarms!r}: {twice[0]!r} is named twice (its legend and "
            "drones would be drawn twice); name each swarm once"
        )
    if shown and "all" in shown and len(shown) > 1:
        raise UserError(
            f"--gui-swarms {args.gui_swarms!r}: 'all' stands alone (it draws every swarm); "
            "give all, or swarms of the run"
        )
    if shown == ["all"]:
        shown = list(swarms)
    record = args.record
    if record is not None and owned is not None and owned[0] is not None:
        folder, what = owned
        if Path(record).resolve().is_relative_to(Path(folder).resolve()):  # links followed
            raise UserError(
                f"--record {record}: lies in {what}, which twin writes afresh (the video would "
                "be lost with it); give a file outside it"
            )
    shown_later = args.gui or args.record
    settings = GuiSettings(swarms=shown, shade=args.gui_shade or "belief", record=args.record)
    check_settings(settings, list(swarms))
    if not shown_later:
        from twin.notices import notify

        for flag, value in (("--gui-swarms", args.gui_swarms), ("--gui-shade", args.gui_shade)):
            if value is not None:
                notify(f"twin: notice: {flag} {value}: draws nothing without --gui or --record")
    return GuiDrawer(settings, list(swarms)) if shown_later else None


def build_experiment(args: argparse.Namespace):
    """The :class:`twin.experiment.Experiment` of ``twin run``'s flags (``twin replay`` rebuilds
    a run's from the flags recorded in its ``run.json``). The flags that set a config key are
    dotted overrides of the scenario config (:func:`twin.cli.recording.with_flags`), validated
    by its models; the swapped-in files go to the live source."""
    from twin.cli.recording import with_flags
    from twin.config import load_config, shipped_config
    from twin.experiment import Experiment, parse_swarm_names
    from twin.resources import check_cell_size
    from twin.sumo.scenario import SumoInputs

    config = load_config(shipped_config(args.config or DEFAULT_CONFIG))
    if config.traffic.kind != "sumo":
        raise UserError(
            f"{config.path}: [traffic].kind = {config.traffic.kind!r}; `twin run` needs "
            '"sumo" (use `twin evaluate` for synthetic traffic)'
        )
    swarms = parse_swarm_names(args.swarms, []) if args.swarms is not None else None
    config = with_flags(
        config,
        {
            "--drones": ("swarm.n_drones", args.drones),
            "--seed": ("evaluate.seed", args.seed),
            "--seeds": ("evaluate.seeds", args.seeds),
            "--swarms": ("evaluate.swarms", swarms),
            "--sumo-seed": ("traffic.seed", args.sumo_seed),
            "--cell-m": ("traffic.cell_m", args.cell_m),
            "--drone-speed": ("traffic.drone_speed_kmh", args.drone_speed),
            "--horizon": ("traffic.horizon", args.horizon),
            "--begin": ("traffic.begin", args.begin),
            "--meso": ("traffic.mesoscopic", True if args.meso else None),
        },
    )
    if args.cell_m is not None:
        check_cell_size(args.cell_m, f"--cell-m {args.cell_m:g}")
    if args.routes and not (args.net or args.sumocfg):
        raise UserError("--routes needs --net or --sumocfg (the network the routes run on)")
    if args.osm is not None and (args.net or args.sumocfg):
        raise UserError(
            "give --osm alone, or --net and/or --sumocfg (--net replaces the sumocfg's)"
        )
    check_count("--workers", args.workers)
    if args.workers > 1 and (args.gui or args.record):
        raise UserError("--gui and --record draw one simulation at a time; drop --workers")
    seeds, first = config.evaluate.seeds, config.evaluate.seed
    count = config.flag_of("evaluate.seeds") or f"{config.path}: [evaluate].seeds"
    check_seeds(config.flag_of("evaluate.seed") or f"{config.path}: [evaluate].seed", first, seeds,
                count)  # fmt: skip
    check_seeds(config.flag_of("traffic.seed") or f"{config.path}: [traffic].seed",
                config.traffic.seed, seeds, count)  # fmt: skip
    return Experiment(
        config=config,
        swarms=config.evaluate.swarms,
        seeds=range(first, first + seeds),
        traffic_options=SumoInputs(
            net=args.net,
            routes=args.routes,
            sumocfg=args.sumocfg,
            osm=args.osm,
            additional=args.additional,
        ).as_kwargs(),
        skip_unavailable=args.swarms is None,
        max_memory_gb=args.max_memory_gb,
        workers=args.workers,
        executor=args.executor,
    )


def main(args: argparse.Namespace) -> int:
    if args.help_config:
        from twin.config import config_help

        print(config_help())
        return 0

    from twin.boundary import hold_notices, notify
    from twin.cli.recording import (
        print_beliefs,
        print_degradation,
        print_tables,
        render_report,
        run_and_record,
    )
    from twin.experiment import limit_threads

    limit_threads()
    hold_notices()  # printed once the simulation has started; a refusal is one line
    experiment = build_experiment(args)
    history = None
    if getattr(args, "history", None) is not None:
        from twin.belief import History, check_source

        history = History.load(args.history)  # a bad file is refused before SUMO starts
    drawer = gui_drawer(args, experiment.swarms, owned=(args.out, f"--out {args.out}"))

    def on_source(source) -> None:
        _announce(source)
        if history is not None:
            check_source(history, args.history, source)
        if drawer is not None:
            drawer.attach(source)
            notify(drawer.legend())

    around = None
    if drawer is not None:
        from twin.sumo.gui import display

        around = display()
    # SUMO's configured outputs: into the run folder, the first seed's in sumo/, the others' in
    # sumo/seed-<s>/
    recorded = run_and_record(
        "run",
        args,
        experiment,
        history,
        on_source,
        extra_meta=lambda outcome: {
            "sumo_read_seconds": round(sum(s.read_seconds for s in outcome.sources), 3)
        },
        outputs_folder="sumo",
        around=around,
        keep_sources=True,
        on_step=drawer,
    )
    outcome, run_dir = recorded.outcome, recorded.run_dir
    first_source = outcome.sources[0]
    video_failed = drawer is not None and args.record and not finish_video(drawer, run_dir)
    done = outcome.stopped
    if outcome.left_out is not None and not outcome.interrupted:
        print(
            f"twin: partial run: {outcome.partial_reason()}; written to {run_dir}", file=sys.stderr
        )
    elif (done.error or done.completed_steps == 0) and not outcome.interrupted:
        print(
            f"twin: partial run: SUMO stopped early ({done.error or 'no step ran'}); results of "
            f"{done.completed_steps} of {first_source.horizon} steps written to {run_dir}",
            file=sys.stderr,
        )
    seeds = [r.seed for r in outcome.results]
    mfd = first_source.model.report()
    from twin.experiment import seed_ranges

    label = f"seed{'s' * (len(seeds) > 1)} {seed_ranges(seeds)}"  # those the tables hold
    title = (
        f"Table 2 analog ({first_source.scenario.name}, {label}, "
        f"T = {outcome.results[0].completed_steps})"
    )
    print_tables(recorded, title)
    print_degradation(run_dir)
    print(
        f"MFD ({mfd['form']}, SUMO seed {first_source.scenario.seed}): a = {mfd['a']:.3f}, "
        f"k_c = {mfd['k_c']:.1f} veh/lane-km, R2 = {mfd.get('r2', float('nan')):.3f}, "
        f"RMSE = {mfd.get('rmse_kmh', float('nan')):.2f} km/h over {mfd['n_samples']} cell samples"
        f"; used: {mfd.get('used', 'fit')} ({mfd.get('why', '')})"
    )
    print_beliefs(recorded.beliefs, args.history, label)
    print(f"wall time {outcome.seconds:.0f} s (SUMO + swarms)")
    if outcome.results and outcome.results[0].stage_seconds:
        from twin.timing import largest_stages

        print(
            f"largest stages of the loop (seed {outcome.results[0].seed}; all in timing.csv): "
            f"{largest_stages(outcome.results[0].stage_seconds)}"
        )
    if not args.no_report:
        render_report(run_dir)
    print(f"run folder: {run_dir}")
    if outcome.interrupted:
        what = (
            f"{outcome.partial_reason()};"
            if outcome.left_out is not None
            else f"partial run of {done.completed_steps} steps (seed {done.seed})"
        )
        print(f"twin: interrupted; {what} written to {run_dir}", file=sys.stderr)
        return 130
    return 1 if outcome.partial or done.completed_steps == 0 or video_failed else 0


def finish_video(drawer, run_dir: Path | None = None) -> bool:
    """Assemble ``--record``'s video after the results are written: whatever goes wrong costs
    only the video (one warning line; an unexpected error's traceback in ``error.log``)."""
    from twin.boundary import describe_os_error, log_traceback, say

    kept = f"the results are written to {run_dir}; " if run_dir is not None else ""
    try:
        print(f"video: {drawer.finish()}", file=sys.stderr)
        return True
    except UserError as exc:
        why = str(exc)
    except OSError as exc:
        why = f"--record: {describe_os_error(exc)}"
    except Exception as exc:  # the video is never worth the run: log it, say it, go on
        log = log_traceback(exc)
        why = f"--record: {type(exc).__name__}: {exc}" + (f" (details in {log})" if log else "")
    say(f"warning: {kept}the video failed: {why}")
    return False


def _announce(source) -> None:
    """The ``SUMO: ...`` line: scenario, grid, drones, the warm-up's start (SUMO's begin, not
    whole steps before T^0), the window and the step."""
    from twin.boundary import notify
    from twin.clock import clock_label

    s = source.scenario
    notify(
        f"SUMO: {s.name} (seed {s.seed}), {source.grid.nx} x {source.grid.ny} cells of "
        f"{source.geometry.cell_m:g} m ({source.grid.n_free} free, "
        f"{s.extra.get('n_drones', '?')} drones), "
        f"{clock_label(s.sim_begin)} warm-up, {source.clock(0)} - "
        f"{source.clock(s.horizon)}, step {s.step_s:g} s"
    )

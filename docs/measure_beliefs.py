"""Score the belief models of a finished `twin run` folder against a history, after the run.

    python docs/measure_beliefs.py --history HISTORY.npz RUN_DIR [RUN_DIR ...] [--spatial] \
        [--meas-var V] [--detector-var V] [--detector-bias B] [--csv OUT.csv] \
        [--per-seed OUT.csv]
    python docs/measure_beliefs.py --detector-error RUN_DIR [RUN_DIR ...]
    python docs/measure_beliefs.py --history HISTORY.npz RUN_DIR --ideal-stations N

Replays each seed's tape (``tapes/seed-<s>.parquet``, else ``tape.parquet``) without SUMO for
the observed and true maps, reads the swarms' positions from ``trajectories.parquet`` and
prints :func:`twin.belief.run_beliefs`' table (mean over seeds), the same numbers as
``twin run --history``; ``--spatial`` adds the nowcast with 4-neighbour coupling. A run that
read fixed detectors (``detectors.parquet``) adds the detectors-only row and each swarm's
``nowcast+detectors``. ``--per-seed`` writes every seed's rows and prints, per swarm and model,
the 95% interval over seeds of the error, calibration and events known (Student's t, as the
Table 2 intervals). ``--detector-error`` prints instead how far the detector stations'
readings lie from their cells' true importance (bias, variance, RMSE over all readings): the
measurement variance of the detectors, to be chosen on validation seeds. ``--ideal-stations
N`` replaces the run's detectors by N stations at the cells of the placement rule
(:func:`twin.sumo.detectors.station_cells` on the tape's lane-km; every free cell with lanes
counts) that read their cell's true importance exactly, filtered with the variance of an exact
sighting (``--meas-var`` when given): a bound on what stations at those cells could add, rows
``(ideal stations only)`` and ``nowcast+ideal``. The drones' sightings have the variance of the
tape's sighting model (:class:`twin.belief.SightingModel`), or ``--meas-var``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd

from twin.belief import (
    DEFAULT_DETECTOR_VAR,
    DETECTORS_ONLY,
    SIGHTING_VAR_FLOOR,
    DetectorObservations,
    History,
    belief_table,
    format_belief_table,
    summarize,
)
from twin.metrics import ci95_halfwidth
from twin.traffic.tape import Tape, TapeTraffic


def seed_results(run_dir: Path, ideal_stations: int = 0, detector_bias: float = 0.0):
    """One result-like object per seed of ``run_dir``: swarms, grid, seed, positions, maps."""
    trajectories = pd.read_parquet(run_dir / "trajectories.parquet")
    detectors = run_dir / "detectors.parquet"
    detectors = pd.read_parquet(detectors) if detectors.is_file() else None
    for seed, frame in trajectories.groupby("seed", sort=True):
        tape = run_dir / "tapes" / f"seed-{seed}.parquet"
        tape = tape if tape.is_file() else run_dir / "tape.parquet"
        source = TapeTraffic(Tape.read(tape), source_name=str(tape))
        observed, truth = [], []
        for importance in source.importance_maps():
            observed.append(np.array(importance, dtype=np.float32))
            t = source.truth_map()
            truth.append(observed[-1] if t is None else np.array(t, dtype=np.float32))
        swarms = list(dict.fromkeys(frame["swarm"]))
        steps = int(frame["step"].max()) + 1
        drones = int(frame["drone"].max()) + 1
        positions = np.zeros((len(swarms), steps, drones, 2), np.int64)
        for s, swarm in enumerate(swarms):
            f = frame[frame["swarm"] == swarm]
            positions[s, f["step"], f["drone"]] = f[["i", "j"]].to_numpy()
        extra = {"sighting": source.sighting_model()}
        if ideal_stations:
            from twin.sumo.detectors import station_cells

            tape_ = source.tape
            free = ~tape_.obstacles & (tape_.lane_km > 0)
            cells = station_cells(tape_.lane_km, free, ideal_stations)
            flat = np.array(sorted(i * source.grid.ny + j for i, j in cells))
            t = np.stack(truth)[:steps].reshape(steps, -1)
            extra["detectors"] = DetectorObservations(flat, t[:, flat].astype(float))
        elif detectors is not None:
            d = detectors[detectors["seed"] == seed]
            extra["detectors"] = DetectorObservations.from_readings(
                zip(
                    d["step"],
                    d["i"] * source.grid.ny + d["j"],
                    (d["importance"] - detector_bias).clip(0.0, 1.0),
                    strict=True,
                ),
                steps - 1,
            )
        yield SimpleNamespace(
            extra=extra,
            swarms=swarms,
            grid=source.grid,
            seed=int(seed),
            positions=positions,
            importance=np.stack(observed)[:steps],
            truth=np.stack(truth)[:steps],
            step_s=source.tape.settings.get("step_s"),
        )


def detector_error(run_dirs) -> None:
    """Station readings against their cells' true importance, over every seed of the runs."""
    errors = []
    for run_dir in run_dirs:
        for r in seed_results(run_dir):
            obs = r.extra.get("detectors")
            if obs is None:
                raise SystemExit(f"{run_dir}: no detectors.parquet (a run without detectors)")
            truth = r.truth.reshape(r.truth.shape[0], -1)[: len(obs.values), obs.cells]
            values = obs.values[: len(truth)]
            ok = np.isfinite(values)
            errors.append((values - truth)[ok])
            print(f"{run_dir}: seed {r.seed}, {len(obs.cells)} stations, {ok.sum()} readings")
    e = np.concatenate(errors)
    print(
        f"reading - truth: bias {e.mean():+.4f}, variance {e.var():.5f}, "
        f"mean square {np.mean(e * e):.5f} (RMSE {np.sqrt(np.mean(e * e)):.4f}), "
        f"median |error| {np.median(np.abs(e)):.4f}, over {len(e)} readings"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", type=Path, nargs="+")
    parser.add_argument("--history", type=Path)
    parser.add_argument("--detector-var", type=float, default=DEFAULT_DETECTOR_VAR)
    parser.add_argument("--detector-error", action="store_true")
    parser.add_argument("--ideal-stations", type=int, default=0)
    parser.add_argument("--detector-bias", type=float, default=0.0, help="subtracted from readings")
    parser.add_argument("--spatial", action="store_true")
    parser.add_argument(
        "--meas-var", type=float, help="one variance for every sighting (default: sighting model)"
    )
    parser.add_argument("--csv", type=Path, help="also write the table here")
    parser.add_argument("--per-seed", type=Path, help="write every seed's rows here")
    args = parser.parse_args()
    if args.detector_error:
        detector_error(args.run_dirs)
        return
    if args.history is None:
        parser.error("--history is required (except with --detector-error)")
    history = History.load(args.history)
    tables = []
    for run_dir in args.run_dirs:
        for r in seed_results(run_dir, args.ideal_stations, args.detector_bias):
            print(f"{run_dir}: seed {r.seed} ({len(r.swarms)} swarms)", flush=True)
            tables.append(
                belief_table(
                    r,
                    history,
                    step_s=r.step_s,
                    meas_var=args.meas_var,
                    spatial=args.spatial,
                    detector_var=(args.meas_var or SIGHTING_VAR_FLOOR)
                    if args.ideal_stations
                    else args.detector_var,
                )
            )
    per_seed = pd.concat(tables, ignore_index=True)
    table = summarize(per_seed)
    if args.ideal_stations:
        table["swarm"] = table["swarm"].replace(DETECTORS_ONLY, "(ideal stations only)")
        table["model"] = table["model"].replace("nowcast+detectors", "nowcast+ideal")
    print(
        f"history {args.history}: rho median {np.median(history.rho[~history.obstacles]):.3f}, "
        f"neighbour correlation {history.neighbour_corr:.3f}"
    )
    print(format_belief_table(table))
    if args.csv:
        table.to_csv(args.csv, index=False)
    if args.per_seed:
        per_seed.to_csv(args.per_seed, index=False)
        print(format_intervals(per_seed))


def format_intervals(per_seed: pd.DataFrame) -> str:
    """Mean ± 95% half-width over seeds of the error, calibration and % events known."""
    lines = ["mean ± 95% interval over seeds (error, calib90, % events known, FA/h):"]
    for (swarm, model), rows in per_seed.groupby(["swarm", "model"], sort=False):
        cells = []
        for column, fmt in [
            ("belief_error", ".4f"),
            ("calibration_90", ".3f"),
            ("pct_events_known", ".1f"),
            ("false_alarms_per_hour", ".1f"),
        ]:
            values = rows[column].dropna().to_numpy(float)
            if len(values) == 0:
                cells.append("-")
                continue
            half = ci95_halfwidth(values) if len(values) > 1 else float("nan")
            cells.append(f"{values.mean():{fmt}} ± {half:{fmt}}")
        lines.append(f"  {swarm:<22} {model:<17} " + "  ".join(cells) + f"  ({len(rows)} seeds)")
    return "\n".join(lines)


if __name__ == "__main__":
    main()

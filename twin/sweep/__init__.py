"""Experiment sweeps: a grid of scenarios x parameters x seeds, each cell one traffic pass with
every swarm side by side, run on a local process pool or on Ray.

A sweep config (TOML, e.g. ``configs/sweep-demo.toml``)::

    [sweep]
    name = "demo"
    swarms = ["random", "greedy", "sweeping"]
    seeds = [0, 1, 2]                 # or: seeds = 3 (and seed = first seed)

    [swarm_options.rl]                # keyword options of make_policy("rl", ...)
    checkpoint = "../data/qnet.pt"    # paths relative to the sweep config

    [[scenario]]
    name = "synthetic"
    config = "synthetic.toml"         # a scenario config, as `twin evaluate`/`twin run` take
    overrides = { "traffic.horizon" = 144 }

    [parameters]                      # every combination is a cell (per scenario and seed)
    "swarm.n_drones" = [2, 4]         # each value once; lists too, e.g. "grid.obstacles" =
                                      # [[], [[1, 1]]] (labelled by their JSON text)

Modules: :mod:`~twin.sweep.config` (the config model), :mod:`~twin.sweep.cells` (expansion,
ids, :func:`run_cell`), :mod:`~twin.executors` (local pool, Ray),
:mod:`~twin.sweep.store` (cell records, manifest, merge), :mod:`~twin.sweep.runner`
(:func:`run_sweep`).

A cell is plain data (a dict) handed to the top-level :func:`run_cell`, so both executors can
ship it; it writes ``cells/<id>.json`` (and the per-step series ``cells/<id>.parquet``)
atomically, and a restarted sweep skips every cell whose JSON exists. The cell's seed fixes
the drones' starts (``default_rng(seed)``, as ``twin evaluate``), the swarms' randomness
(``run_patrol``) and the traffic's, so the same seeds give the same numbers on either
executor and in ``twin evaluate``.
"""

from twin.executors import EXECUTORS, Outcome
from twin.sweep.cells import (
    DEFINING_KEYS,
    cell_id,
    code_fingerprint,
    expand_cells,
    file_sha256,
    parameter_combinations,
    run_cell,
    scenario_config,
)
from twin.sweep.config import ScenarioSpec, SweepConfig, load_sweep_config
from twin.sweep.runner import SweepOutcome, check_cells, prepare_sumo, run_sweep
from twin.sweep.store import (
    CELLS_DIR,
    KEY_COLUMNS,
    done_cells,
    merge,
    write_cell_record,
    write_sweep_report,
)

__all__ = [
    "CELLS_DIR",
    "DEFINING_KEYS",
    "EXECUTORS",
    "KEY_COLUMNS",
    "Outcome",
    "ScenarioSpec",
    "SweepConfig",
    "SweepOutcome",
    "cell_id",
    "check_cells",
    "code_fingerprint",
    "done_cells",
    "expand_cells",
    "file_sha256",
    "load_sweep_config",
    "merge",
    "parameter_combinations",
    "prepare_sumo",
    "run_cell",
    "run_sweep",
    "scenario_config",
    "write_cell_record",
    "write_sweep_report",
]

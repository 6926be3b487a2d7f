"""``twin pretrain``: pretrain the universal Q-function on a random swarm's experience."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from twin.cli import path_arg

DEFAULT_CONFIG = "configs/pretrain.toml"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "pretrain",
        help="pretrain the Q-network (Double DQN on a random swarm's transitions)",
        description="Collect transitions of a randomly moving swarm on the training map, then "
        "train the Table 1 Q-network with Double DQN (Sec. III-A). Writes <out>/qnet.pt (the "
        "model), <out>/train_log.csv (loss and mean Q) and <out>/state.pt (checkpoint every "
        "checkpoint_every epochs). Running the same command again resumes from state.pt.",
    )
    p.add_argument("--config", type=path_arg, default=None,
                   help=f"pretraining config (TOML); default {DEFAULT_CONFIG}")  # fmt: skip
    p.add_argument("--out", default=None, help="output folder (overrides the config's `out`)")
    p.add_argument("--epochs", type=int, default=None, help="overrides the config's `epochs`")
    p.add_argument("--traffic", type=path_arg, nargs="+", default=None, metavar="TAPE",
                   help='train on these SUMO tapes (tape.parquet of `twin run`): the recipe '
                   'traffic = "tapes" (other recipes: the config key `traffic`, see '
                   "--help-config)")  # fmt: skip
    p.add_argument("--init", type=path_arg, default=None, metavar="QNET",
                   help="start from this model checkpoint (fine-tuning); the config key `init`")  # fmt: skip
    p.add_argument("--max-memory-gb", type=float, default=None,
                   help="memory limit in GB (default $TWIN_MAX_MEMORY_GB, else 8)")  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--help-config", action="store_true",
                   help="list every config key with its default and meaning, then exit")  # fmt: skip
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from twin.boundary import claim_new_folder, hold_notices, release_notices, set_run_folder
    from twin.config import shipped_config
    from twin.outputs import check_output_dir
    from twin.training.pretrain import (
        check_out_folder,
        check_pretrain_memory,
        load_config,
        pretrain,
    )

    if args.help_config:
        print(pretrain_config_help())
        return 0
    hold_notices()  # printed once training starts; a refusal is one line
    config = load_config(  # the flags are overrides of the config's keys, named in an error
        shipped_config(args.config or DEFAULT_CONFIG),
        out=args.out,
        epochs=args.epochs,
        tapes=None if args.traffic is None else [str(Path(t).absolute()) for t in args.traffic],
        init=None if args.init is None else str(Path(args.init).absolute()),
    )
    where = str(args.config or DEFAULT_CONFIG)
    check_pretrain_memory(config, where, args.max_memory_gb)
    flag = "--out" if args.out else f"{where}: out"
    check_output_dir(  # the model, its checkpoints and snapshots
        config.out,
        flag,
        need_mb=200,
        owner=lambda _: check_out_folder(config, flag),  # resumes its own, refuses the rest
    )
    out = Path(config.out)
    another = None if args.out else f"give another out in {where}, or --out"
    made = claim_new_folder(out, flag, another)  # one pretraining at a time writes into it
    set_run_folder(out)  # an unexpected error's traceback goes to its error.log
    progress = not args.quiet and sys.stderr.isatty()
    release_notices()  # every check passed: training starts
    try:
        path = pretrain(config, progress=progress, max_memory_gb=args.max_memory_gb)
    except BaseException:  # refused or stopped before it wrote: no empty folder left
        if made and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
    print(f"model: {path}")
    print(f"log: {Path(config.out) / 'train_log.csv'}")
    return 0


def pretrain_config_help() -> str:
    """Every key of a pretraining config with its default and meaning, then the scenario's
    keys pretraining reads (with the training map's values): what ``--help-config`` prints."""
    from twin.training.pretrain import SCENARIO_KEYS, TRAINING_MAP, PretrainConfig

    lines = []
    for name, f in PretrainConfig.model_fields.items():
        default = f.get_default(call_default_factory=True)
        lines.append(f"{name:22s} {default!s:24s} {f.description or ''}")
    scenario = PretrainConfig().training_map
    lines.append(
        f"\nThe scenario's keys pretraining reads (values of {TRAINING_MAP}, the default "
        "`scenario`; change them there or in scenario_overrides; obstacles, z_lo, z_hi too):"
    )
    for key in SCENARIO_KEYS.values():
        table, name = key.split(".")
        value = getattr(getattr(scenario, table), name)
        if name == "disturbances":
            value = f"{len(value)} disturbances (4 big, 3 small)"
        lines.append(f"{key:22s} {value!s}")
    lines.append(
        "\nRecipes: traffic = paper | dynamics | tapes (--traffic TAPE ...); init = a "
        "checkpoint to fine-tune (--init); collector = random (the paper) | coordinated "
        "(the rl swarm being learned, epsilon-greedy: collect_every, epsilon_start, "
        "epsilon_end, epsilon_decay_epochs); n_step with gamma (1: the paper's 1-step "
        "target); state = paper (the 13 values of eq. s) | window (5 x 5 cells) | nowcast "
        "(plus the nowcast's mean and std on the view cells; history_days, history_seed), "
        "the first layer sized to it. "
        "curve_every > 0 writes curve.csv (R_hat_T on curve_seeds against updates); "
        "provenance.json records command, recipe, scenario, seeds, schedule, wall time and "
        "curve. --out, --epochs, --traffic and --init set the keys out, epochs, tapes (with "
        "traffic) and init."
    )
    return "\n".join(lines)

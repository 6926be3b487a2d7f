"""The ``twin`` command: one module per subcommand in this package.

Each subcommand module exposes ``add_parser(subparsers)``, which registers its parser with
``set_defaults(func=main)``, and ``main(args) -> int``. A module listed in :data:`COMMANDS`
that does not exist is skipped.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from twin import __version__
from twin.errors import UserError

COMMANDS = ["evaluate", "pretrain", "network", "run", "report", "sweep"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twin",
        description="A SUMO digital twin patrolled by a learning drone swarm "
        "(Maljkovic & Geroliminis, 'On Learning-Based Traffic Monitoring With a Swarm of Drones').",
    )
    parser.add_argument("--version", action="version", version=f"twin {__version__}")
    subparsers = parser.add_subparsers(title="commands", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"twin.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"twin.cli.{name}":
                continue
            raise
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"twin: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("twin: interrupted; files already written are complete", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

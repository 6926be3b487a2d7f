"""The ``twin`` command: one module per subcommand in this package.

Each subcommand module exposes ``add_parser(subparsers)``, which registers its parser with
``set_defaults(func=main)``, and ``main(args) -> int``. A module listed in :data:`COMMANDS`
that does not exist is skipped. :func:`main` runs the chosen one through
:func:`twin.boundary.run_command`, the one place where an escaping exception becomes a one-line
message and an exit code (listed there).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

from twin import __version__
from twin.boundary import run_command, set_command_line
from twin.errors import UserError
from twin.seeds import MAX_SEED

COMMANDS = [
    "evaluate", "pretrain", "network", "run", "history", "report", "sweep", "replay", "transfer",
]  # fmt: skip


def path_arg(text: str) -> Path:
    """The value of a path argument; an empty one (``--out ''``) is refused rather than read
    as the current folder."""
    if text == "":
        raise argparse.ArgumentTypeError("an empty path; give a file or folder name")
    return Path(text)


def check_count(flag: str, value: int | None) -> None:
    """A count flag (``--seeds``, ``--horizon``, ``--epochs``, ...) must be at least 1."""
    if value is not None and value < 1:
        raise UserError(f"{flag} = {value} is below 1; give a whole number of at least 1")


def check_seeds(
    flag: str, first: int | None, count: int = 1, count_flag: str = "", least: int = 1
) -> None:
    """Seeds ``first .. first + count - 1`` must lie in ``0 .. MAX_SEED``: a first seed out of
    range is ``flag``'s fault, too many seeds from a good one ``count_flag``'s (which takes at
    least ``least``: the fix offered is one both flags take)."""
    if first is None:
        return
    if first < 0 or first > MAX_SEED or (first + count - 1 > MAX_SEED and not count_flag):
        last = f" (with {count} seeds: up to {first + count - 1})" if count > 1 else ""
        raise UserError(
            f"{flag} = {first} is out of range{last}; seeds are whole numbers from 0 to {MAX_SEED}"
        )
    if first + count - 1 > MAX_SEED:
        room = MAX_SEED - first + 1
        fixes = [f"at most {room}"] if room >= least else []
        if count <= MAX_SEED + 1:  # a smaller first seed fits them all
            fixes.append(f"{flag} at most {MAX_SEED - count + 1}")
        raise UserError(
            f"{count_flag} = {count} runs seeds {first} .. {first + count - 1}, past the largest "
            f"seed {MAX_SEED}; give {', or '.join(fixes) or f'at most {MAX_SEED + 1} seeds'}"
        )


def add_worker_arguments(p, live: bool = True) -> None:
    """``--workers``, ``--executor`` (``twin run``: ``live``, ``twin evaluate``)."""
    what = "SUMO simulation" if live else "seed"
    why = (
        "a seed already uses more than one core, SUMO working ahead of the swarms in its own "
        "process (on 2 shared cores 2 workers gained nothing, docs/benchmarks.md), and each "
        "worker holds a whole simulation in memory"
        if live
        else "each worker holds a whole run in memory and starts a fresh interpreter, a few "
        "seconds that short seeds do not repay"
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help=f"seeds run at once, each {what} with its swarms in a worker process of its own; "
        f"same results as one after another (default 1, one after another: {why}; this "
        f"machine has {os.cpu_count()} CPUs)",
    )
    p.add_argument(
        "--executor",
        choices=("local", "ray"),
        default="local",
        help="where --workers run: a local process pool (default) or a local Ray (pip install "
        "'twin[ray]')",
    )


def add_scoring_arguments(p) -> None:
    """What ``twin run`` and ``twin evaluate`` share after their traffic: the memory limit, the
    ceilings, the history of belief models, the report, progress bars and the config's keys."""
    p.add_argument(
        "--max-memory-gb",
        type=float,
        default=None,
        help="refuse a run whose estimated memory exceeds this (default $TWIN_MAX_MEMORY_GB or 8)",
    )
    p.add_argument(
        "--ceiling",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="add the rows oracle (ceiling) and bound (ceiling): a swarm planning on the true "
        "future maps and an upper bound no swarm can exceed, computed after the swarms' run "
        "(default on, left out of a run stopped by Ctrl-C; --no-ceiling skips them)",
    )
    p.add_argument(
        "--history",
        type=path_arg,
        help="a history of earlier days (`twin history`): also score each swarm's belief "
        "models (last-seen, history, nowcast) and write belief_models.csv",
    )
    p.add_argument("--no-report", action="store_true", help="do not render the HTML report")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--help-config", action="store_true",
                   help="list every table and key of a scenario config with its default, "
                   "then exit")  # fmt: skip


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (the flag, the problem, where the help is)
    and exit code 2, like every other refusal of twin."""

    def error(self, message: str):
        from twin.boundary import EXIT_REFUSED, say

        say(f"error: {self.prog}: {message}; see `{self.prog} --help`")
        self.exit(EXIT_REFUSED)


class _Refused(Exception):
    """A command line :func:`parse_command_line` cannot parse."""


class _QuietParser(Parser):
    """A parser whose errors are raised, not said: it reads back a recorded command line."""

    def error(self, message: str):
        raise _Refused(message)

    def exit(self, status=0, message=None):
        raise _Refused(message or "--help or --version")


def build_parser(parser_class: type[argparse.ArgumentParser] = Parser) -> argparse.ArgumentParser:
    return _build_parser(parser_class)[0]


def _build_parser(parser_class):
    """The ``twin`` parser of class ``parser_class`` and its subcommands' parsers by name."""
    parser = parser_class(
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
    return parser, subparsers.choices


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` and run its command, both inside the boundary (an import that fails while
    the parser is built is one line too)."""
    return run_command(_dispatch, argv)


def _dispatch(argv: list[str] | None) -> int:
    set_command_line(argv)  # run.json records these arguments, not the process's
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    check_utf8_arguments(parser, args)
    return int(args.func(args) or 0)


def check_command_line(path: Path, run: dict) -> None:
    """run.json's ``command`` (``path``) is a command line twin takes, giving the options its
    ``invocation`` records, and no other: the report shows that line as the command that made
    the run. An option the recording twin did not have yet must be left at its default."""
    import contextlib
    import io
    import json

    from twin.readback import RERUN, command_words
    from twin.runs import invocation

    command, recorded = run.get("command"), run.get("invocation")
    if not isinstance(command, str) or not isinstance(recorded, dict):
        return
    recorded = recorded.get("options")
    kind = run.get("kind")
    if not isinstance(recorded, dict) or not isinstance(kind, str):
        return
    shown = repr(command)[:80]
    try:
        words = command_words(command)
        if words is None:
            raise _Refused("no twin command line as a shell reads it")
        parser, commands = _build_parser(_QuietParser)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            args = parser.parse_args(words[1:])
    except _Refused as exc:
        raise UserError(
            f"{path}: command = {shown} is no twin command line ({exc}); {RERUN}"
        ) from None
    if kind not in commands:
        return
    sub = commands[kind]
    flags = _argument_names(sub)
    given = json.loads(json.dumps(invocation(kind, args)["options"], default=str))
    unknown = sorted(set(recorded) - set(given))
    if unknown:
        raise UserError(
            f"{path}: invocation.options.{unknown[0][:40]} is not an option of `twin {kind}`; "
            f"{RERUN}"
        )
    for option, value in given.items():
        want = recorded[option] if option in recorded else sub.get_default(option)
        want = json.loads(json.dumps(want, default=str))
        if value != want:
            raise UserError(
                f"{path}: command = {shown} gives {flags.get(option, option)} "
                f"{repr(value)[:40]}, but invocation.options.{option} = {repr(want)[:40]}; "
                f"{RERUN}"
            )


def check_utf8_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse (one line naming the argument) a file name or other argument that is not valid
    UTF-8 (bytes such as 0xff, which Python holds as surrogates): libsumo cannot take it, nor
    twin's JSON files and reports. SUMO's own programs open such files, but twin runs SUMO
    through libsumo."""
    names = _argument_names(parser)
    for dest, value in vars(args).items():
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if not isinstance(item, (str, Path)) or _is_utf8(str(item)):
                continue
            shown = os.fsencode(str(item)).decode("utf-8", "backslashreplace")
            raise UserError(
                f"{names.get(dest, dest)} '{shown}': the name is not valid UTF-8; give a name "
                "in UTF-8 (rename the file or folder, or link to it under such a name: ln -s)"
            )


def _is_utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _argument_names(parser: argparse.ArgumentParser) -> dict[str, str]:
    """Each argument's destination -> its name on the command line (``--net``, ``RUN_DIR``),
    over the parser and its subcommands."""
    names: dict[str, str] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                for dest, name in _argument_names(sub).items():
                    names.setdefault(dest, name)
        elif action.option_strings:
            names.setdefault(action.dest, max(action.option_strings, key=len))
        else:
            names.setdefault(action.dest, action.metavar or action.dest.upper())
    return names


if __name__ == "__main__":
    sys.exit(main())

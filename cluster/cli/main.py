"""The ``ocv2`` command line.

    ocv2 --version
    ocv2 layouts [--show NAME]          the built-in kitchens (table, or one ASCII map with a legend)
    ocv2 render LAYOUT --steps N --out FILE.gif [--seed S] [--fps F] [--view-radius V] [--tile-size T]
    ocv2 render --seats SEAT0 SEAT1 --out FILE.gif [--greedy]   one episode of two trained policies
    ocv2 train CONFIG [--set section.key=value ...] [--out RUN_DIR] [--resume] [--logger NAME]
    ocv2 xp RUN_DIR [--episodes N]      cross-play of one run
    ocv2 xp --rows SRC ... [--cols SRC ...] [--checkpoint C] [--greedy] [--out DIR]   across runs (docs/evaluation.md)
    ocv2 export SRC --out FILE [--force] [--seed I] [--checkpoint C]   one policy to one file (never into a run)
    ocv2 verify FOLDER [FOLDER ...]      published policies against their SHA256SUMS.json
    ocv2 study run STUDY.yaml [--budget F] [--seeds N] [--out DIR] | status DIR | report DIR   studies
    ocv2 validate CONFIG [CONFIG ...] [--set section.key=value ...]
    ocv2 report RUN_DIR [RUN_DIR ...] [--out DIR]
    ocv2 button-game [--buttons N] [--seeds S] [--out DIR]
    ocv2 archive info|replay|recover FILE ...   MCAP trajectory archives (docs/archive.md)
    ocv2 play [LAYOUT] [--partner RUN_DIR/checkpoints/seed_i|human] [--seat S] [--port P]   human play (docs/play.md)
    ocv2 human import SOURCE | proxy LAYOUT --source SOURCE   2019 human games, BC human proxy (docs/human.md)

Global options, before the command: ``-v`` shows debug records, ``-q`` only warnings and errors (no
progress; ``ocv2 -q train ...`` is ``ocv2 train --quiet ...``).

Each subcommand is one function that declares its arguments and one that runs it and returns an exit
code; ``COMMANDS`` lists them. The bigger ones live in the module named after them
(``cluster/cli/<command>.py``; ``ocv2 study``'s subcommands in ``study.py``) and are named by string: a
command's module is imported only when that command runs (``ocv2 layouts`` never imports the trainer,
Ray or the play server). Errors the user can fix raise ``CLIError`` and become a one-line
message on stderr and exit code 2 (usage) or 1 (failure), never a traceback; so does an ``OSError`` that
reaches ``main`` (a full disk, a read-only folder) in any command, with the command's advice
(``args.os_error_advice``) or the general one.

Results (tables, "wrote FILE", the run directory) go to stdout; progress, warnings and errors are log
records of the packages' module loggers, which ``configure_logging`` sends to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.metadata
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import NamedTuple

from rich.console import Console
from rich.table import Table

from cluster.cli.args import layout_or_error, resolved
from cluster.cli.errors import (  # noqa: F401 (EXIT_* re-exported)
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    CLIError,
    os_error_message,
)
from cluster.runtime.interrupt import ChunkAbandoned, StoppedAfterChunk, exit_now, jax_started
from ocv2.layouts import LAYOUTS, Layout

# ---------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------


def _console(stream=None):
    stream = sys.stdout if stream is None else stream
    # Not a terminal (pipes, tests): wide enough that layout names are never wrapped.
    width = None if stream.isatty() else 200
    return Console(file=stream, width=width, highlight=False, soft_wrap=False)


# ---------------------------------------------------------------------------------------------------
# ocv2 layouts
# ---------------------------------------------------------------------------------------------------


def _add_layouts(sub) -> argparse.ArgumentParser:
    parser = sub.add_parser(
        "layouts",
        help="list the built-in kitchen layouts",
        description="List every built-in layout, or print one layout's ASCII map.",
    )
    parser.add_argument("--show", metavar="NAME", help="print the ASCII map of layout NAME")
    return parser


#: What each character of ``Layout.to_string`` stands for (``ocv2.layouts`` builds maps from the same).
LEGEND = {
    "W": "counter",
    "X": "delivery",
    "B": "plate pile",
    "P": "pot",
    "R": "recipe indicator",
    "L": "button recipe indicator",
    "A": "agent start",
    " ": "floor",
}


def legend(layout: Layout) -> list[str]:
    """One line per character the map uses (ingredient piles named by ingredient index)."""
    used = set(layout.to_string())
    lines = [f"  {char if char != ' ' else '(space)':7} {meaning}" for char, meaning in LEGEND.items() if char in used]
    piles = sorted(char for char in used if char.isdigit())
    lines += [f"  {char:7} pile of ingredient {char}" for char in piles]
    return lines


def _cmd_layouts(args) -> int:
    if args.show is not None:
        layout = layout_or_error(args.show)
        print(
            f"{layout.name}: {layout.height}x{layout.width}, {layout.num_agents} agents, "
            f"{layout.num_ingredients} ingredients, recipes {[list(r) for r in layout.possible_recipes]}"
        )
        print(layout.to_string())
        print("legend:")
        print("\n".join(legend(layout)))
        return EXIT_OK

    table = Table(title=f"{len(LAYOUTS)} OvercookedV2 layouts")
    table.add_column("name", no_wrap=True)
    table.add_column("HxW", justify="right", no_wrap=True)
    table.add_column("agents", justify="right")
    table.add_column("ingredients", justify="right")
    table.add_column("recipes")
    for name, layout in LAYOUTS.items():
        recipes = ", ".join(str(list(r)) for r in layout.possible_recipes)
        table.add_row(
            name, f"{layout.height}x{layout.width}", str(layout.num_agents), str(layout.num_ingredients), recipes
        )
    _console().print(table)
    return EXIT_OK


# ---------------------------------------------------------------------------------------------------
# logging
# ---------------------------------------------------------------------------------------------------

#: The loggers of the three packages: the library modules log under these names, never print.
PACKAGE_LOGGERS = ("ocv2", "population", "cluster")


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (a rich bar or a test may have replaced it)."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        """The current ``sys.stderr``."""
        return sys.stderr

    @stream.setter
    def stream(self, _value):
        """Ignore the stream ``logging`` sets: records always go to the current ``sys.stderr``."""
        pass


class _Formatter(logging.Formatter):
    """Progress as it is; a warning or an error says so in front; debug records name their module."""

    def format(self, record: logging.LogRecord) -> str:
        """``record``'s message, prefixed by ``error:``, ``warning:`` or ``debug MODULE:`` by its level."""
        message = super().format(record)
        if record.levelno >= logging.ERROR:
            return f"error: {message}"
        if record.levelno >= logging.WARNING:
            return f"warning: {message}"
        if record.levelno < logging.INFO:
            return f"debug {record.name}: {message}"
        return message


def _ours_or_a_warning(record: logging.LogRecord) -> bool:
    """The packages' records at their loggers' level; another library's only from WARNING up."""
    return record.name.split(".")[0] in PACKAGE_LOGGERS or record.levelno >= logging.WARNING


_handler = _StderrHandler()
_handler.setFormatter(_Formatter())
_handler.addFilter(_ours_or_a_warning)


def configure_logging(verbosity: int = 0) -> None:
    """Show log records on stderr: the packages' from INFO, from DEBUG (``verbosity`` > 0) or only from
    WARNING (< 0); other libraries' warnings and errors. One handler, installed once on the root logger
    however often ``main`` runs in a process: with a root handler in place, libraries that call
    ``logging.basicConfig`` on first use (absl, through optax) add no second one that repeats every line."""
    level = logging.DEBUG if verbosity > 0 else logging.WARNING if verbosity < 0 else logging.INFO
    for name in PACKAGE_LOGGERS:
        logging.getLogger(name).setLevel(level)
    root = logging.getLogger()
    if _handler not in root.handlers:
        root.addHandler(_handler)


# ---------------------------------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------------------------------


class Command(NamedTuple):
    """One ``ocv2`` subcommand: its name, its help line, and the functions (or "module:function" names,
    imported only when the command runs) that declare its parser and run it."""

    name: str
    help: str  # the one-liner of ``ocv2 --help`` (the command's own parser repeats it; a test checks)
    add: Callable | str  # declares the subparser; "module:function" names one imported when needed
    run: Callable | str


#: The order is the help listing's.
COMMANDS: list[Command] = [
    Command("layouts", "list the built-in kitchen layouts", _add_layouts, _cmd_layouts),
    Command(
        "render",
        "render an episode to a GIF: random actions, or two trained policies (--seats)",
        "cluster.cli.render:add_render",
        "cluster.cli.render:run_render",
    ),
    Command(
        "train", "train a population from a YAML config", "cluster.cli.train:add_train", "cluster.cli.train:run_train"
    ),
    Command(
        "xp",
        "cross-play matrix of a trained population, or across runs and policy files",
        "cluster.cli.xp:add_xp",
        "cluster.cli.xp:run_xp",
    ),
    Command(
        "export",
        "write one policy (params + network + env settings) to a file",
        "cluster.cli.export:add_export",
        "cluster.cli.export:run_export",
    ),
    Command(
        "verify",
        "check published policies folders against their SHA256SUMS.json",
        "cluster.cli.verify:add_verify",
        "cluster.cli.verify:run_verify",
    ),
    Command(
        "study",
        "run many population jobs and their comparisons as one resumable study",
        "cluster.cli.study:add_parser",
        "cluster.cli.study:run",
    ),
    Command(
        "validate",
        "check YAML configs without running anything",
        "cluster.cli.validate:add_validate",
        "cluster.cli.validate:run_validate",
    ),
    Command(
        "report",
        "paper-style SP/XP tables, curves and heatmaps of run directories",
        "cluster.cli.report:add_report",
        "cluster.cli.report:run_report",
    ),
    Command(
        "button-game",
        "the paper's Button Game: IQL self-play pairs, a best response, cross-play",
        "cluster.cli.button_game:add_parser",
        "cluster.cli.button_game:run",
    ),
    Command(
        "archive",
        "inspect, replay or recover an MCAP trajectory archive",
        "cluster.cli.archive:add_parser",
        "cluster.cli.archive:run",
    ),
    Command(
        "play",
        "play in the browser with a trained agent or another person (recorded to MCAP)",
        "cluster.cli.play:add_play",
        "cluster.cli.play:run_play",
    ),
    Command(
        "human",
        "2019 human-human trials: import as archives, train a BC human proxy",
        "cluster.cli.human:add_parser",
        "cluster.cli.human:run",
    ),
]


def resolve(target: Callable | str) -> Callable:
    """A function, or the one a "module:function" string names (importing its module now)."""
    if callable(target):
        return target
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def version() -> str:
    """The installed ocv2 package's version, or a note saying it is not installed."""
    try:
        return importlib.metadata.version("ocv2")
    except importlib.metadata.PackageNotFoundError:  # run from a checkout that was never pip-installed
        return "unknown (not installed; pip install -e .)"


def _chosen_command(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names (the top-level parser has no option that takes a value)."""
    return next((arg for arg in argv if not arg.startswith("-")), None)


def build_parser(argv: Sequence[str] = (), full: bool = False) -> argparse.ArgumentParser:
    """The parser, with the arguments of the command ``argv`` names only (``full``: of every command)."""
    parser = argparse.ArgumentParser(prog="ocv2", description="OvercookedV2 in pure JAX: layouts, rendering, training.")
    parser.add_argument("--version", action="version", version=f"ocv2 {version()}")
    parser.add_argument(
        "-v",
        "--verbose",
        dest="log_verbose",
        action="store_true",
        help="also show debug messages (before the command: ocv2 -v train ...)",
    )
    parser.add_argument(
        "-q",
        "--quiet",
        dest="log_quiet",
        action="store_true",
        help="only warnings and errors: no progress (before the command: ocv2 -q train ...)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    chosen = _chosen_command(argv)
    for command in COMMANDS:
        if full or command.name == chosen:
            resolve(command.add)(sub).set_defaults(func=command.run)
        else:
            sub.add_parser(command.name, help=command.help)
    return parser


@contextlib.contextmanager
def _sigterm_as_ctrl_c():
    """SIGTERM stops a command as Ctrl-C does (a training run saves its chunk in flight first), where it would
    otherwise end the process at once: a job started in the background ignores SIGINT, so SIGTERM is how a
    script (study_state/stop_and_pack.py) or a service manager stops it gracefully. Restored afterwards."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _check_links_resolve(args) -> None:
    """A CLIError for a path argument whose symbolic links lead back to themselves: every layer resolves the
    paths it is given, and Python 3.11-3.12 raise a RuntimeError there (3.13's OSError is worded below)."""
    for name, flag in (("out", "--out"), ("dir", ""), ("source", ""), ("study", "")):
        value = getattr(args, name, None)
        if isinstance(value, str):
            resolved(value, flag)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``ocv2`` command line; returns the exit code (0 ok, 1 failure, 2 usage error)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:  # argparse already printed usage / help
        return exit_.code if isinstance(exit_.code, int) else EXIT_USAGE
    if args.log_verbose and args.log_quiet:
        print("ocv2: error: -v and -q contradict each other; give one", file=sys.stderr)
        return EXIT_USAGE
    if isinstance(getattr(args, "out", None), str) and not args.out.strip():  # "$OUT" of an unset variable
        print(f"ocv2 {args.command}: error: --out: an empty path (an unset variable?)", file=sys.stderr)
        return EXIT_USAGE
    if args.log_quiet and hasattr(args, "quiet"):
        args.quiet = True  # the command's own --quiet also turns its progress bar off
    quiet = args.log_quiet or getattr(args, "quiet", False) is True
    configure_logging(1 if args.log_verbose else -1 if quiet else 0)
    try:
        _check_links_resolve(args)
        with _sigterm_as_ctrl_c():
            code = int(resolve(args.func)(args))
        sys.stdout.flush()  # inside the try: a reader gone before the last buffered write is caught here
        return code
    except CLIError as error:
        print(f"ocv2 {args.command}: error: {error}", file=sys.stderr)
        return error.code
    except KeyboardInterrupt as interrupt:
        print(f"ocv2 {args.command}: interrupted", file=sys.stderr)
        # A jitted chunk abandoned by a second Ctrl-C still runs, and one that lands outside a chunk's wait
        # (a compile, cross-play) may: a normal exit would wait for it, or abort under running XLA threads.
        # Everything of the command's own (files, Ray) was closed on the way here.
        if isinstance(interrupt, ChunkAbandoned) or (not isinstance(interrupt, StoppedAfterChunk) and jax_started()):
            exit_now(130)
        return 130
    except BrokenPipeError:
        return _reader_gone()
    except OSError as error:  # a full disk, a read-only or vanished folder, in any command: one line
        advice = getattr(args, "os_error_advice", None)
        advice = advice() if callable(advice) else advice  # a command may advise by what it had done by then
        print(f"ocv2 {args.command}: error: {os_error_message(error, advice)}", file=sys.stderr)
        return EXIT_FAILURE


def _reader_gone() -> int:
    """stdout's reader closed early (``ocv2 ... | head``): exit quietly, as a killed-by-SIGPIPE tool would.

    Python ignores SIGPIPE, so writes raise instead. stdout is pointed at /dev/null so that the
    interpreter's final flush of what is still buffered does not fail a second time at exit.
    """
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # stdout replaced by an object without a descriptor
        pass
    return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""The ``ocv2`` command line.

    ocv2 layouts [--show NAME]          the built-in kitchens (table, or one ASCII map)
    ocv2 render LAYOUT --steps N --out FILE.gif [--seed S] [--fps F] [--view-radius V] [--tile-size T]
    ocv2 train CONFIG [--set section.key=value ...] [--out RUN_DIR] [--resume]
    ocv2 xp RUN_DIR [--episodes N]      cross-play of one run
    ocv2 xp --rows SRC ... [--cols SRC ...] [--checkpoint C] [--greedy] [--out DIR]   across runs (docs/evaluation.md)
    ocv2 export SRC --out FILE [--seed I] [--checkpoint C]   one policy to one file
    ocv2 validate CONFIG [CONFIG ...] [--set section.key=value ...]
    ocv2 report RUN_DIR [RUN_DIR ...] [--out DIR]
    ocv2 button-game [--buttons N] [--seeds S] [--out DIR]
    ocv2 archive info|replay|recover FILE ...   MCAP trajectory archives (docs/archive.md)
    ocv2 play [LAYOUT] [--partner RUN_DIR/checkpoints/seed_i|human] [--seat S] [--port P]   human play (docs/play.md)
    ocv2 human import SOURCE | proxy LAYOUT --source SOURCE   2019 human games, BC human proxy (docs/human.md)

Each subcommand is one function that declares its arguments and one that runs it and returns an exit
code; ``COMMANDS`` lists them (the bigger ones live in ``cluster/cmd_*.py`` and are imported lazily). Errors the user can fix raise ``CLIError`` and become a
one-line message on stderr and exit code 2 (usage) or 1 (failure), never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Callable, Sequence

from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, CLIError  # noqa: F401 (re-exported)


# ---------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------

def _console(stream=None):
    from rich.console import Console

    stream = sys.stdout if stream is None else stream
    # Not a terminal (pipes, tests): wide enough that layout names are never wrapped.
    width = None if stream.isatty() else 200
    return Console(file=stream, width=width, highlight=False, soft_wrap=False)


def _layout_or_error(name: str):
    from ocv2.layouts import get_layout

    try:
        return get_layout(name)
    except ValueError as error:  # its message names the layout, lists the choices and suggests close ones
        raise CLIError(str(error)) from None


def _int_at_least(minimum: int, what: str):
    """An argparse type: an integer >= ``minimum``, with a message naming ``what`` was expected."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {what} integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected a {what} integer, got {value}")
        return value

    return parse


_positive_int = _int_at_least(1, "positive")
_non_negative_int = _int_at_least(0, "non-negative")


def _fps(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected frames per second (a number), got {text!r}") from None
    if not 0 < value <= 100:
        raise argparse.ArgumentTypeError(f"fps must be > 0 and <= 100, got {text}")
    return value


# ---------------------------------------------------------------------------------------------------
# ocv2 layouts
# ---------------------------------------------------------------------------------------------------

def _add_layouts(sub) -> argparse.ArgumentParser:
    parser = sub.add_parser("layouts", help="list the built-in kitchen layouts",
                            description="List every built-in layout, or print one layout's ASCII map.")
    parser.add_argument("--show", metavar="NAME", help="print the ASCII map of layout NAME")
    return parser


def _cmd_layouts(args) -> int:
    from ocv2.layouts import LAYOUTS

    if args.show is not None:
        layout = _layout_or_error(args.show)
        print(f"{layout.name}: {layout.height}x{layout.width}, {layout.num_agents} agents, "
              f"{layout.num_ingredients} ingredients, recipes {[list(r) for r in layout.possible_recipes]}")
        print(layout.to_string())
        return EXIT_OK

    from rich.table import Table

    table = Table(title=f"{len(LAYOUTS)} OvercookedV2 layouts")
    table.add_column("name", no_wrap=True)
    table.add_column("HxW", justify="right", no_wrap=True)
    table.add_column("agents", justify="right")
    table.add_column("ingredients", justify="right")
    table.add_column("recipes")
    for name, layout in LAYOUTS.items():
        recipes = ", ".join(str(list(r)) for r in layout.possible_recipes)
        table.add_row(name, f"{layout.height}x{layout.width}", str(layout.num_agents), str(layout.num_ingredients),
                      recipes)
    _console().print(table)
    return EXIT_OK


# ---------------------------------------------------------------------------------------------------
# ocv2 render
# ---------------------------------------------------------------------------------------------------

def _add_render(sub) -> argparse.ArgumentParser:
    parser = sub.add_parser("render", help="render a random-action episode to a GIF",
                            description="Play uniformly random actions on LAYOUT and write the frames "
                                        "(the reset state plus one per step) to a looping GIF.")
    parser.add_argument("layout", help="layout name (see 'ocv2 layouts')")
    parser.add_argument("--steps", type=_non_negative_int, default=50, help="transitions to play (default 50)")
    parser.add_argument("--out", required=True, help="GIF file to write")
    parser.add_argument("--seed", type=int, default=0, help="PRNG seed (default 0)")
    parser.add_argument("--fps", type=_fps, default=5.0, help="frames per second (default 5)")
    parser.add_argument("--view-radius", type=_non_negative_int, default=None,
                        help="highlight every cell within this radius of an agent (default: none)")
    parser.add_argument("--tile-size", type=_positive_int, default=32, help="pixels per cell (default 32)")
    return parser


def _cmd_render(args) -> int:
    import os

    layout = _layout_or_error(args.layout)
    if not args.out.lower().endswith(".gif"):
        raise CLIError(f"--out must name a .gif file, got {args.out!r}")
    folder = os.path.dirname(os.path.abspath(args.out))
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise CLIError(f"--out: {folder!r} exists and is not a folder")
    os.makedirs(folder, exist_ok=True)  # like the run directories to come: create what is missing

    import jax

    import ocv2
    from ocv2.render import render_frames, rollout_states, write_gif

    env = ocv2.make(layout)
    states = rollout_states(env, jax.random.PRNGKey(args.seed), args.steps)
    frames = render_frames(states, layout, agent_view_size=args.view_radius, tile_size=args.tile_size)
    try:
        path = write_gif(frames, args.out, fps=args.fps)
    except OSError as error:
        raise CLIError(f"could not write {args.out!r}: {error}", EXIT_FAILURE) from None
    height, width = frames.shape[1:3]
    print(f"wrote {path}: {len(frames)} frames ({args.steps} steps of {layout.name}), {width}x{height} px, "
          f"{args.fps:g} fps")
    return EXIT_OK


# ---------------------------------------------------------------------------------------------------
# entry point
# ---------------------------------------------------------------------------------------------------

def _lazy(module: str, name: str) -> Callable:
    """``module.name``, imported on first call: ``ocv2 layouts`` never pays for importing the trainer."""

    def call(*args):
        return getattr(importlib.import_module(module), name)(*args)

    return call


#: (name, add-arguments function, run function); the order is the help listing's.
COMMANDS: list[tuple[str, Callable, Callable]] = [
    ("layouts", _add_layouts, _cmd_layouts),
    ("render", _add_render, _cmd_render),
    ("train", _lazy("cluster.cli.train", "add_train"), _lazy("cluster.cli.train", "run_train")),
    ("xp", _lazy("cluster.cli.xp", "add_xp"), _lazy("cluster.cli.xp", "run_xp")),
    ("export", _lazy("cluster.cli.xp", "add_export"), _lazy("cluster.cli.xp", "run_export")),
    ("validate", _lazy("cluster.cli.report", "add_validate"), _lazy("cluster.cli.report", "run_validate")),
    ("report", _lazy("cluster.cli.report", "add_report"), _lazy("cluster.cli.report", "run_report")),
    ("button-game", _lazy("cluster.cli.button_game", "add_parser"), _lazy("cluster.cli.button_game", "run")),
    ("archive", _lazy("cluster.cli.archive", "add_parser"), _lazy("cluster.cli.archive", "run")),
    ("play", _lazy("cluster.cli.play", "add_play"), _lazy("cluster.cli.play", "run_play")),
    ("human", _lazy("cluster.cli.human", "add_parser"), _lazy("cluster.cli.human", "run")),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ocv2", description="OvercookedV2 in pure JAX: layouts, rendering, training.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for _name, add, run in COMMANDS:
        add(sub).set_defaults(func=run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``ocv2`` command line; returns the exit code (0 ok, 1 failure, 2 usage error)."""
    parser = build_parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as exit_:  # argparse already printed usage / help
        return exit_.code if isinstance(exit_.code, int) else EXIT_USAGE
    try:
        return int(args.func(args))
    except CLIError as error:
        print(f"ocv2 {args.command}: error: {error}", file=sys.stderr)
        return error.code
    except KeyboardInterrupt:
        print(f"ocv2 {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

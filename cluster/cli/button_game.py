"""``ocv2 button-game``: train the Button Game population and write its cross-play matrix.

    ocv2 button-game [--buttons N] [--seeds 10] [--out DIR] [--seed S] [--episodes E]
                     [--epsilon EPS] [--lr LR]

Writes ``DIR/button_game_xp.csv`` (labelled matrix, rows Alices, columns Bobs) and
``DIR/button_game_xp.png`` (annotated heatmap), and prints the SP, XP and BR means.
``cluster.cli.main.COMMANDS`` names this module by string: it is imported only when the command runs.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from cluster.cli.args import bounded
from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from population.button_game import ButtonGameConfig, IQLConfig, plot_heatmap, run_button_game, write_csv

DEFAULT_OUT = os.path.join("runs", "button_game")
DEFAULT_BUTTONS = ButtonGameConfig().num_buttons
DEFAULT_EPISODES = IQLConfig().episodes
DEFAULT_EPSILON = IQLConfig().epsilon
DEFAULT_LR = IQLConfig().learning_rate
CSV_NAME = "button_game_xp.csv"
PNG_NAME = "button_game_xp.png"


def add_parser(sub) -> argparse.ArgumentParser:
    """Declare ``button-game`` and its arguments; out-of-range values are argparse usage errors."""
    parser = sub.add_parser(
        "button-game",
        help="the paper's Button Game: IQL self-play pairs, a best response, cross-play",
        description="Train SEEDS self-play Alice/Bob pairs with tabular independent Q-learning and a Bob that "
        "best-responds to a uniformly random Alice, then write the cross-play matrix (exact "
        "expected reward of greedy policies) as CSV and as a heatmap PNG.",
    )
    positive = "an integer in [1, {}]".format
    parser.add_argument(
        "--buttons",
        metavar="N",
        type=bounded(int, 2, 10_000, "an integer in [2, 10000]"),
        default=DEFAULT_BUTTONS,
        help=f"number of buttons N (2N bulbs; default {DEFAULT_BUTTONS})",
    )
    parser.add_argument(
        "--seeds",
        metavar="SEEDS",
        type=bounded(int, 1, 100, positive(100)),
        default=10,
        help="self-play pairs to train (default 10)",
    )
    parser.add_argument("--out", metavar="DIR", default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    parser.add_argument("--force", action="store_true", help="replace the results of an earlier run in --out")
    parser.add_argument(
        "--seed",
        metavar="S",
        type=bounded(int, 0, 2**32 - 1, "an integer in [0, 2**32)"),
        default=0,
        help="root PRNG seed; pair i uses fold_in(PRNGKey(seed), i) (default 0)",
    )
    parser.add_argument(
        "--episodes",
        metavar="E",
        type=bounded(int, 1, 10_000_000, positive(10_000_000)),
        default=DEFAULT_EPISODES,
        help=f"training games per agent (default {DEFAULT_EPISODES})",
    )
    parser.add_argument(
        "--epsilon",
        metavar="EPS",
        type=bounded(float, 0.0, 1.0, "a number in [0, 1]"),
        default=DEFAULT_EPSILON,
        help=f"epsilon-greedy exploration rate (default {DEFAULT_EPSILON:g})",
    )
    parser.add_argument(
        "--lr",
        metavar="LR",
        type=bounded(float, 0.0, 1.0, "a number in (0, 1]", low_open=True),
        default=DEFAULT_LR,
        help=f"Q-learning rate (default {DEFAULT_LR:g})",
    )
    return parser


def _configs(args):
    """Build the configs (argparse types have already range-checked every flag)."""
    try:
        return (
            ButtonGameConfig(num_buttons=args.buttons),
            IQLConfig(episodes=args.episodes, epsilon=args.epsilon, learning_rate=args.lr),
        )
    except ValueError as error:  # pragma: no cover - the argparse types reject these first
        raise CLIError(str(error)) from None


def run(args) -> int:
    """Train, evaluate, write CSV + PNG, print the means; returns the exit code."""

    game, iql = _configs(args)
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise CLIError(f"--out: {args.out!r} exists and is not a folder")
    if os.path.isfile(os.path.join(args.out, "config.yaml")):
        raise CLIError(f"--out {args.out}: is a run directory; give a folder of its own")
    earlier = [name for name in (CSV_NAME, PNG_NAME) if os.path.exists(os.path.join(args.out, name))]
    if earlier and not args.force:
        raise CLIError(
            f"--out {args.out}: holds {' and '.join(earlier)} of an earlier run; pass --force to replace them, "
            "or give a new folder"
        )
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as error:
        raise CLIError(f"could not create {args.out!r}: {error}", EXIT_FAILURE) from None

    start = time.perf_counter()
    result = run_button_game(seed=args.seed, num_seeds=args.seeds, game=game, iql=iql)
    seconds = time.perf_counter() - start

    csv_path = os.path.join(args.out, CSV_NAME)
    png_path = os.path.join(args.out, PNG_NAME)
    title = (
        f"Button Game cross-play (N={game.num_buttons}, {args.seeds} SP pairs, "
        f"{iql.episodes} games, eps={iql.epsilon:g}, lr={iql.learning_rate:g}, seed {args.seed})"
    )
    written = [csv_path]
    try:
        write_csv(csv_path, result.matrix, result.labels)
        plot_heatmap(png_path, result.matrix, result.labels, title=title)
        written.append(png_path)
    except ImportError as error:  # matplotlib is the optional plots extra: the numbers stand without the picture
        print(f"warning: {png_path} not drawn: {error}; pip install 'ocv2[plots]'", file=sys.stderr)
    except OSError as error:
        raise CLIError(f"could not write to {args.out!r}: {error}", EXIT_FAILURE) from None

    xp = "n/a (one pair)" if args.seeds < 2 else f"{result.xp_mean:+.2f}"
    print(
        f"button game: N={game.num_buttons} buttons, {args.seeds} self-play pairs + 1 best response, "
        f"{iql.episodes} games each, epsilon {iql.epsilon:g}, lr {iql.learning_rate:g}, seed {args.seed} "
        f"({seconds:.1f} s)"
    )
    print(f"  SP  (diagonal, SP pairs)          {result.sp_mean:+.2f}")
    print(f"  XP  (off-diagonal, SP pairs)      {xp}")
    print(f"  BR  (BR Bob with every SP Alice)  {result.br_mean:+.2f}")
    print(f"  BR Bob with the random Alice      {result.br_random_alice:+.2f}")
    print(f"wrote {' and '.join(written)}")
    return EXIT_OK

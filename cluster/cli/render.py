"""``ocv2 render``: one episode to a looping GIF, of random actions or of two trained policies.

    ocv2 render LAYOUT --out FILE.gif [--steps N] [--seed S] [--fps F] [--view-radius V] [--tile-size T]
    ocv2 render --seats SEAT0 SEAT1 --out FILE.gif [--steps N] [--seed S] [--greedy] [--precision P] [...]

With ``--seats`` the two policies (``ocv2 export`` files, run directories or checkpoint files, as
``population.policy.load`` reads them) play one episode of the environment they were trained in, seat 0
first, sampled unless ``--greedy``: the published policies of a study become a picture of what a pair
does, e.g. two seeds on different conventions failing together. The episode's return is printed, so a
GIF can be set beside the cross-play matrix cell it is one episode of. The episode is traced at the matmul
precision the policies trained with (``run.precision``, from a checkpoint's run or an exported file's meta;
float32 where nothing says), as cross-play plays them (``cluster.runtime.crossplay.played_precision``): seats
that trained at different precisions are refused unless ``--precision`` chooses one.
"""

from __future__ import annotations

import argparse
import os
from types import SimpleNamespace

import jax

import ocv2
from cluster.cli.args import add_gif_options, check_new_file, layout_or_error, non_negative_int, seed
from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from cluster.runtime import crossplay
from ocv2.render import check_frame_size, render_frames, rollout_states, write_gif
from population import policy as policies
from population.config import PRECISIONS
from population.evaluation import episode_states
from population.numerics import matmul_precision

HELP = "render an episode to a GIF: random actions, or two trained policies (--seats)"
RANDOM_STEPS = 50  # random actions: a short clip unless --steps says otherwise


def add_render(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 render`` on ``sub`` (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "render",
        help=HELP,
        description="Write one episode's frames (the reset state plus one per step) to a looping GIF: "
        "uniformly random actions on LAYOUT, or the two policies of --seats in the environment they were "
        "trained in.",
    )
    parser.add_argument("layout", nargs="?", help="layout name (see 'ocv2 layouts'); with --seats, optional")
    parser.add_argument(
        "--seats",
        nargs=2,
        metavar=("SEAT0", "SEAT1"),
        help="two trained policies to play instead of random actions: ocv2 export files, run directories "
        "(seed 0's final checkpoint) or checkpoint files",
    )
    parser.add_argument(
        "--steps",
        type=non_negative_int,
        default=None,
        help=f"transitions to show (default {RANDOM_STEPS}; with --seats the whole episode)",
    )
    parser.add_argument("--greedy", action="store_true", help="with --seats: argmax actions instead of sampled")
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        help="with --seats: matmul precision the episode is played at (default: the run.precision the policies "
        "trained with, as cross-play plays them; a choice is required when they trained at different ones)",
    )
    parser.add_argument("--seed", type=seed, default=0, help="PRNG seed (default 0)")
    add_gif_options(parser)
    return parser


def run_render(args) -> int:
    """Write the GIF ``args`` asks for; returns ``EXIT_OK``. Raises ``CLIError`` for an unknown layout, an
    --out that is not a new .gif, an episode too big for memory, seats that are no policies or play other
    environments, and a LAYOUT that is not the seats'."""
    if not args.out.lower().endswith(".gif"):
        raise CLIError(f"--out must name a .gif file, got {args.out!r}")
    if args.seats:
        seats = [_load_seat(flag, source) for flag, source in zip(("SEAT0", "SEAT1"), args.seats)]
        env = _shared_env(seats, args.layout)
        precision = _played_precision(seats, args.precision)
        steps = env.max_steps if args.steps is None else args.steps
        if steps > env.max_steps:
            raise CLIError(f"--steps {steps}: an episode of {env.layout.name} has {env.max_steps} steps")
    else:
        if args.layout is None:
            raise CLIError("give a LAYOUT to render random actions on, or two policies with --seats")
        if args.greedy:
            raise CLIError("--greedy applies to --seats: random actions have no argmax")
        if args.precision is not None:
            raise CLIError("--precision applies to --seats: random actions use no network")
        env = ocv2.make(layout_or_error(args.layout))
        steps = RANDOM_STEPS if args.steps is None else args.steps
    layout = env.layout
    try:  # the frames of one GIF live in memory together: the reset state plus one per step
        check_frame_size(layout, args.tile_size, frames=steps + 1)
    except ValueError as error:
        raise CLIError(f"--steps {steps} with --tile-size {args.tile_size}: {error}") from None
    check_new_file("--out", args.out, force=args.force)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)  # create what is missing
    key = jax.random.PRNGKey(args.seed)
    if args.seats:
        states, episode_return = _seats_episode(seats, env, key, args.greedy, precision)
        states = jax.tree.map(lambda x: x[: steps + 1], states)
        what = f"{steps} steps of {layout.name}, {seats[0].name} and {seats[1].name}"
    else:
        states, episode_return = rollout_states(env, key, steps), None
        what = f"{steps} steps of {layout.name}"
    frames = render_frames(states, layout, agent_view_size=args.view_radius, tile_size=args.tile_size)
    try:
        path = write_gif(frames, args.out, fps=args.fps)
    except OSError as error:
        raise CLIError(f"could not write {args.out!r}: {error}", EXIT_FAILURE) from None
    height, width = frames.shape[1:3]
    print(f"wrote {path}: {len(frames)} frames ({what}), {width}x{height} px, {args.fps:g} fps")
    if episode_return is not None:
        print(f"episode return {episode_return:g} over the whole {env.max_steps}-step episode (seed {args.seed})")
    return EXIT_OK


def _load_seat(flag: str, source: str) -> policies.Policy:
    try:
        return policies.load(source)
    except policies.PolicyError as error:
        raise CLIError(f"--seats {flag}: {error}") from None


def _shared_env(seats: list, layout: str | None) -> ocv2.OvercookedV2:
    """The environment both seats were trained in; a CLIError when they differ or LAYOUT is another."""
    first, second = seats
    if not policies.same_env(first.env, second.env):
        raise CLIError(
            f"--seats: {second.source} plays another environment than {first.source} "
            f"({policies.env_difference(second.env, first.env)})"
        )
    env = first.make_env()
    if layout is not None and layout != env.layout.name:
        raise CLIError(f"LAYOUT {layout!r}: the --seats policies play {env.layout.name!r}; leave LAYOUT out")
    return env


def _played_precision(seats: list, chosen: str | None) -> str:
    """The ``run.precision`` the seats' episode is traced at: ``chosen``, else the one they trained with (the
    default where neither says), as cross-play decides it; a CLIError for a precision that is not one, or for
    seats of different precisions when nothing was chosen."""

    known = []
    for flag, seat in zip(("SEAT0", "SEAT1"), seats):
        try:
            precision = policies.trained_precision(seat)
        except policies.PolicyError as error:
            raise CLIError(f"--seats {flag}: {seat.source}: {error}") from None
        known.append(SimpleNamespace(label=seat.source, precision=precision))
    try:
        return crossplay.played_precision(known, chosen)
    except crossplay.CrossPlayError as error:
        raise CLIError(f"--seats: {error}; choose one with --precision") from None


def _seats_episode(seats: list, env, key: jax.Array, greedy: bool, precision: str):
    """One whole episode of the two seats: every state (the reset one, then one per step) and its team sparse
    return, traced at ``precision`` (a ``run.precision`` name). Jitted: un-jitted, each of the episode's steps
    would dispatch its ops one by one."""
    play = jax.jit(lambda k: episode_states([s.seat for s in seats], env, k, greedy))
    with matmul_precision(precision):
        states, episode_return = play(key)
    return states, float(episode_return)

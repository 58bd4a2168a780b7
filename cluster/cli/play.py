"""``ocv2 play``: play OvercookedV2 in the browser with a trained agent or another person (``docs/play.md``).

    ocv2 play [LAYOUT] [--partner RUN_DIR/checkpoints/seed_i | CHECKPOINT | FILE.ocv2policy | human | stay | random]
              [--seat 0|1] [--host H] [--port P] [--fps F] [--agent-view-size V] [--max-steps N]
              [--env KEY=VALUE ...] [--out FILE.mcap] [--seed S] [--episodes N] [--meta KEY=VALUE ...]

Starts a local web server, prints its URL and records every played episode to an MCAP archive
(``docs/archive.md``) until Ctrl-C (or ``--episodes`` episodes). ``cluster.cli.main`` imports this
module only when ``ocv2 play`` runs.
"""

from __future__ import annotations

import argparse
import errno
import ipaddress
import os
import secrets
import signal
import threading
import time

import yaml

import ocv2
from cluster.archive import RESERVED_KEYS, ArchiveError, ArchiveWriter
from cluster.cli.args import (
    bounded,
    check_not_under_a_file,
    fps,
    int_at_least,
    layout_or_error,
    non_negative_int,
    positive_int,
)
from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from cluster.play.game import PartnerError, human_partner, load_policy_partner, make_game, scripted_partner, warm_up
from cluster.play.server import PlayServer
from cluster.play.session import PLAY_META_KEYS, SEAT_COLOURS, GameSession
from ocv2.config import build_config
from ocv2.render import check_frame_size
from population.config import ConfigError, check_plain_data, load_yaml_text, yaml_problem

DEFAULT_PORT = 8765
DEFAULT_HOST = "127.0.0.1"
PARTNER_KINDS = ("human", "stay", "random")


def _key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key.strip(), value


def add_play(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 play`` on ``sub`` (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "play",
        help="play in the browser with a trained agent or another person (recorded to MCAP)",
        description="Start a local web server for human play: arrow keys move, space interacts, the game "
        "advances at a fixed tick (stay when no key is pressed). Every episode is recorded to an "
        "MCAP archive (ocv2 archive info|replay FILE). See docs/play.md.",
    )
    parser.add_argument(
        "layout", nargs="?", help="layout name (see 'ocv2 layouts'); optional with a policy partner (the run's layout)"
    )
    parser.add_argument(
        "--partner",
        default="stay",
        metavar="WHO",
        help="RUN_DIR/checkpoints/seed_<i> (its latest checkpoint), a checkpoint file in it or an exported "
        "policy file (FILE.ocv2policy, e.g. under docs/results/*/policies/); 'human' (a second browser tab plays "
        "the other seat); 'stay' or 'random' "
        "(scripted; default stay)",
    )
    parser.add_argument(
        "--seat",
        type=non_negative_int,
        default=0,
        help="the human's seat, 0 (red) or 1 (blue); with --partner human, the first tab's seat (default 0)",
    )
    parser.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help=f"address to listen on (default {DEFAULT_HOST}: this machine only; 0.0.0.0 lets other machines join)",
    )
    parser.add_argument(
        "--port",
        type=bounded(int, 0, 65535, "a port number 0..65535 (0: any free port)"),
        default=DEFAULT_PORT,
        help=f"TCP port (default {DEFAULT_PORT}; 0 picks a free one)",
    )
    parser.add_argument("--fps", type=fps, default=5.0, help="environment steps per second (default 5)")
    parser.add_argument(
        "--agent-view-size",
        type=non_negative_int,
        default=None,
        metavar="V",
        help="view radius: each player sees only the cells within V of their cook",
    )
    parser.add_argument(
        "--max-steps",
        type=positive_int,
        default=None,
        metavar="N",
        help="steps per episode (default the env's 400, or the partner run's)",
    )
    parser.add_argument(
        "--env",
        type=_key_value,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="any other ocv2.make parameter (YAML value), e.g. --env sample_recipe_on_delivery=true",
    )
    parser.add_argument(
        "--tile-size",
        type=int_at_least(8, "tile size (>= 8)"),
        default=48,
        help="pixels per grid cell of the picture (default 48; a frame is at most a 4K screen's pixels)",
    )
    parser.add_argument(
        "--out", metavar="FILE.mcap", help="archive to record to (default runs/play/<layout>_<time>.mcap)"
    )
    parser.add_argument(
        "--seed",
        type=bounded(int, 0, 2**32 - 1, "an integer in [0, 2**32)"),
        default=None,
        help="root PRNG seed (default: random, and recorded in every episode's metadata)",
    )
    parser.add_argument(
        "--episodes",
        type=positive_int,
        default=None,
        metavar="N",
        help="stop after N recorded episodes (default: run until Ctrl-C)",
    )
    parser.add_argument(
        "--meta",
        type=_key_value,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra metadata for every episode, e.g. --meta participant=P07 (repeatable)",
    )
    parser.add_argument(
        "--disconnect-timeout",
        type=bounded(float, 0, 3600, "seconds in (0, 3600]", low_open=True),
        default=10.0,
        metavar="S",
        help="a tab silent this many seconds has left: its episode ends (default 10)",
    )
    parser.add_argument("--verbose", action="store_true", help="log every HTTP request")
    return parser


def run_play(args) -> int:
    """Serve the game ``args`` describes in the browser until its episodes are played, Ctrl-C or SIGTERM,
    recording every episode (the one in progress too) to an MCAP archive. Returns ``EXIT_OK``; raises
    ``CLIError`` for a bad partner, layout, seat or option, an address it cannot listen on, an archive it
    cannot create, or a game that failed."""
    partner = _partner(args.partner)
    env = _env(args, partner)
    human_seats = _human_seats(args, env, partner)
    _check_tile_size(args.tile_size, env, human_seats)
    meta = _meta(args.meta)
    server = _bind(args.host, args.port, args.verbose)
    writer = failure = None
    previous = _interrupt_on_sigterm()
    try:
        writer, path = _writer(args.out, env.layout.name, args.fps)

        seed = secrets.randbits(31) if args.seed is None else args.seed
        print(f"ocv2 play: preparing {env.layout.name} (compiling the game takes a few seconds)...", flush=True)
        game = make_game(env, partner, human_seats, args.tile_size)
        warm_up(game)
        session = GameSession(
            game,
            writer,
            seed=seed,
            fps=args.fps,
            first_seat=args.seat,
            disconnect_s=args.disconnect_timeout,
            max_episodes=args.episodes,
            meta=meta,
        )
        server.start(session)
        _announce(args, server, game, seed, path)
        try:
            while not session.finished.wait(0.5):
                pass
        except KeyboardInterrupt:
            print("\nocv2 play: stopping")
        failure = session.failure
    finally:
        # A second Ctrl-C or SIGTERM while the archive is being finished would leave a .partial file (and could
        # abort the interpreter mid-cleanup): both are ignored until it is whole (SIGKILL still ends it).
        held = _hold_interrupts()
        try:
            server.stop()  # records the episode in progress, cut short
            recorded = _finish(writer)
        finally:
            for signum, handler in held.items():
                signal.signal(signum, handler)
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
    if failure:
        raise CLIError(failure + (f"; {recorded} episode(s) were recorded to {path}" if recorded else ""), EXIT_FAILURE)
    if recorded:
        print(
            f"recorded {recorded} episode(s) to {path}; replay one with: "
            f"ocv2 archive replay {path} --episode 0 --out episode.gif"
        )
    else:
        print("no episode was played: nothing recorded")
    return EXIT_OK


# ---------------------------------------------------------------------------------------------------
# checks (each a CLIError with a message, never a traceback)
# ---------------------------------------------------------------------------------------------------


def _partner(text: str):

    try:
        if text == "human":
            return human_partner()
        if text in PARTNER_KINDS:
            return scripted_partner(text)
        return load_policy_partner(text)
    except PartnerError as error:
        raise CLIError(str(error)) from None


def _env_flags(args) -> dict:
    flags = {}
    for key, text in args.env:
        if key == "layout":
            raise CLIError("--env layout=...: give the layout as the LAYOUT argument")
        try:  # read as --set reads a value: depth and alias limits, no dates or sets
            flags[key] = load_yaml_text(text) if text.strip() else None
            check_plain_data(flags[key], key)
        except yaml.YAMLError as error:
            raise CLIError(f"--env {key}=...: not a YAML value: {yaml_problem(error)}") from None
        except ConfigError as error:
            raise CLIError(f"--env {key}=...: {'; '.join(error.problems)}") from None
    for key in ("agent_view_size", "max_steps"):
        if getattr(args, key) is not None:
            flags[key] = getattr(args, key)
    return flags


def _env(args, partner):
    """The env to play: the partner run's eval env (checked against LAYOUT and flags), else LAYOUT + flags."""

    flags = _env_flags(args)
    if partner.kind == "policy":
        trained = partner.env_kwargs
        if args.layout is not None and layout_or_error(args.layout).name != trained["layout"]:
            raise CLIError(
                f"the partner was trained on layout {trained['layout']!r}, not {args.layout!r}; "
                "omit LAYOUT or pick a partner trained on it"
            )
        try:
            wanted = build_config(**{**trained, **flags})
        except (TypeError, ValueError) as error:
            raise CLIError(f"environment parameters: {error}") from None
        reference = build_config(**trained)
        differ = [
            f"{key}: the partner's run uses {getattr(reference, key)!r}, you asked for {getattr(wanted, key)!r}"
            for key in flags
            if getattr(wanted, key) != getattr(reference, key)
        ]
        if differ:
            raise CLIError(
                "the partner plays the environment it was evaluated in (its run's config.yaml, or "
                "the exported file's); " + "; ".join(differ) + ". Omit those flags"
            )
        return ocv2.make(**trained)
    if args.layout is None:
        raise CLIError("give a LAYOUT (see 'ocv2 layouts'), or a trained --partner whose run fixes it")
    layout = layout_or_error(args.layout)
    try:
        return ocv2.make(layout, **flags)
    except (TypeError, ValueError) as error:
        raise CLIError(f"environment parameters: {error}") from None


def _human_seats(args, env, partner) -> list[int]:
    seats = env.num_agents
    if args.seat >= seats:
        raise CLIError(f"--seat {args.seat}: layout {env.layout.name!r} has {seats} seat(s) (0..{seats - 1})")
    if partner.kind in ("human", "policy") and seats < 2:
        raise CLIError(f"layout {env.layout.name!r} has one cook: there is no seat for a partner")
    return list(range(seats)) if partner.kind == "human" else [args.seat]


def _check_tile_size(tile_size: int, env, human_seats) -> None:
    # Before the server binds: a huge picture would take GBs and seconds per tick (or be killed) later.
    try:
        check_frame_size(env.layout, tile_size, frames=len(human_seats))
    except ValueError as error:
        raise CLIError(f"--tile-size {tile_size}: {error}") from None


def _meta(pairs) -> dict:

    meta = dict(pairs)
    taken = sorted(set(meta) & set(RESERVED_KEYS + PLAY_META_KEYS))
    if taken:
        raise CLIError(f"--meta {', '.join(taken)}: set by ocv2 play itself; choose other names")
    return meta


def _bind(host: str, port: int, verbose: bool):

    try:
        return PlayServer(host, port, verbose)
    except OSError as error:
        if error.errno == errno.EADDRINUSE:
            raise CLIError(
                f"port {port} on {host} is in use (another 'ocv2 play'?); pass --port with another "
                "number, or --port 0 for any free one",
                EXIT_FAILURE,
            ) from None
        raise CLIError(f"cannot listen on {host}:{port}: {error.strerror or error}", EXIT_FAILURE) from None


def _writer(out: str | None, layout: str, fps: float):

    path = out or os.path.join("runs", "play", f"{layout}_{time.strftime('%Y%m%d-%H%M%S')}.mcap")
    if not path.endswith(".mcap"):
        raise CLIError(f"--out must name a .mcap file, got {path!r}")
    check_not_under_a_file("--out", path)
    for existing, why in ((path, ""), (path + ".partial", " (an unfinished recording: `ocv2 archive recover` it)")):
        if os.path.exists(existing):
            raise CLIError(f"--out {existing}: exists{why}; give a new file name (a recording is never replaced)")
    try:
        # Message times a tick apart: Foxglove and other MCAP players replay the episode at the speed it was played.
        return ArchiveWriter(path, step_ns=round(1e9 / fps), fsync=True).open(), path
    except ArchiveError as error:
        raise CLIError(f"--out: {error}") from None
    except OSError as error:
        raise CLIError(f"cannot create {path!r}: {error}", EXIT_FAILURE) from None


def _finish(writer) -> int:
    """Finish the archive; an archive without episodes is removed (no empty files from a test start)."""
    if writer is None:
        return 0
    writer.close()
    if writer.episodes_written == 0 and os.path.exists(writer.path):
        os.unlink(writer.path)
    return writer.episodes_written


def _announce(args, server, game, seed: int, path: str) -> None:

    env, partner = game.env, game.partner
    view = "" if env.config.view_radius is None else f", view radius {env.config.view_radius}"
    if partner.kind == "human":
        who = f"two people, seats {game.human_seats} (open the page in two tabs or browsers)"
    else:
        seat = game.human_seats[0]
        who = f"you are seat {seat} ({SEAT_COLOURS[seat]}) with partner {partner.label}"
    print(f"ocv2 play: {env.layout.name}, {who}, {env.max_steps} steps at {args.fps:g} steps/s{view}, seed {seed}")
    print(f"recording to {path}")
    if not _loopback(args.host):
        print(
            f"note: listening on {args.host}: other machines join at "
            f"http://<this machine's name or address>:{server.port}/?key={server.key}; give that address only to "
            "your players (the key is the only password)"
        )
    print(f"open {server.url}   (Ctrl-C to stop)", flush=True)


def _interrupt_on_sigterm():
    """Make SIGTERM (``kill``, a service manager) stop like Ctrl-C: the episode in progress is recorded.

    Returns the previous handler, or None where handlers cannot be set (not the main thread).
    """
    if threading.current_thread() is not threading.main_thread():
        return None

    def interrupt(_signum, _frame):
        """Raise ``KeyboardInterrupt``, as Ctrl-C does."""
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, interrupt)


def _hold_interrupts() -> dict:
    """Ignore SIGINT and SIGTERM (main thread only); returns the handlers to put back."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {signum: signal.signal(signum, signal.SIG_IGN) for signum in (signal.SIGINT, signal.SIGTERM)}


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"

"""Arguments the ``ocv2`` subcommands share: argparse ``type=`` callables, ``--set``, the layout lookup.

A bad value is an ``argparse.ArgumentTypeError`` (a usage line naming the flag and the value, exit
code 2); an unknown layout is a ``CLIError`` whose message lists the choices and suggests close ones.
"""

from __future__ import annotations

import argparse
import errno
import os
from collections.abc import Callable, Sequence
from pathlib import Path

from cluster.cli.errors import CLIError
from ocv2.layouts import Layout, get_layout
from population.config import MAX_SEED, is_update_number


def layout_or_error(name: str) -> Layout:
    """The built-in layout ``name``, or a ``CLIError`` naming it."""
    try:
        return get_layout(name)
    except ValueError as error:  # its message names the layout, lists the choices and suggests close ones
        raise CLIError(str(error)) from None


def check_new_folder(flag: str, out: str) -> None:
    """Refuse, before any work, an output folder that is a file, lies under a file or already holds files:
    a command that writes results into a new folder never writes over earlier ones."""
    path = Path(out)
    for parent in reversed([path, *path.parents]):
        if parent.exists() and not parent.is_dir():
            where = "is a file" if parent == path else f"lies under {parent}, which is a file"
            raise CLIError(f"{flag} {out}: {where}; give a new directory")
    if path.is_dir() and any(path.iterdir()):
        raise CLIError(f"{flag} {out}: already holds files (earlier results?); give a new directory")


def check_not_under_a_file(flag: str, out: str) -> None:
    """Refuse an output file whose nearest existing parent is a file."""
    for parent in Path(out).parents:
        if parent.exists():
            if not parent.is_dir():
                raise CLIError(f"{flag} {out}: lies under {parent}, which is a file; give a file in a folder")
            break


def resolved(path, flag: str = "") -> Path:
    """``Path(path).resolve()``, or a ``CLIError`` naming ``flag`` and ``path`` where its symbolic links lead back
    to themselves: Python 3.11 and 3.12 raise a ``RuntimeError`` there, 3.13 returns the path unresolved (and
    ``os.stat`` says ELOOP on every version)."""
    where = f"{flag} " if flag else ""
    try:
        os.stat(path)
    except OSError as error:
        if error.errno == errno.ELOOP:
            raise CLIError(
                f"{where}{path}: its symbolic links cannot be followed ({error.strerror}); {_LOOP}"
            ) from None
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as error:
        raise CLIError(f"{where}{path}: its symbolic links cannot be followed ({error}); {_LOOP}") from None


_LOOP = "a link on the way leads back to itself: remove the loop or give another path"


def check_new_file(flag: str, out: str, force: bool = False) -> None:
    """Refuse an output file that exists (unless ``force``), is a folder, or lies under a file."""
    path = Path(out)
    check_not_under_a_file(flag, out)
    if path.is_dir():
        raise CLIError(f"{flag} {out}: is a directory; give a file name")
    if path.exists() and not path.is_file():
        raise CLIError(f"{flag} {out}: exists and is not a regular file; give a new file name")
    if path.exists() and not force:
        raise CLIError(f"{flag} {out}: exists; pass --force to replace it, or give a new file name")


# JAX counts steps, radii and indices in int32; a larger number would overflow deep inside a jitted function.
MAX_INT = 2**31 - 1


def int_at_least(minimum: int, what: str, maximum: int = MAX_INT) -> Callable[[str], int]:
    """An argparse type: an integer in [``minimum``, ``maximum``], with a message naming ``what`` was expected."""

    def parse(text: str) -> int:
        """``text`` as an integer; raises ``argparse.ArgumentTypeError`` if it is not one or is out of range."""
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {what} integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected a {what} integer, got {value}")
        if value > maximum:
            below = "below 2**31 (JAX counts in int32)" if maximum == MAX_INT else f"at most {maximum}"
            raise argparse.ArgumentTypeError(f"expected a {what} integer {below}, got {value}")
        return value

    return parse


positive_int = int_at_least(1, "positive")
non_negative_int = int_at_least(0, "non-negative")


def bounded(parse: Callable[[str], float], low, high, what: str, low_open: bool = False) -> Callable[[str], float]:
    """An argparse type: ``parse(text)`` within ``[low, high]`` (``(low, high]`` if ``low_open``)."""

    def check(text: str):
        """``parse(text)``; raises ``argparse.ArgumentTypeError`` if it fails, is out of range or is NaN."""
        try:
            value = parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        too_low = value <= low if low_open else value < low
        if too_low or value > high or value != value:  # value != value: NaN
            raise argparse.ArgumentTypeError(f"expected {what}, got {text}")
        return value

    return check


def seed(text: str) -> int:
    """A PRNG seed: JAX's keys hold 32 bits, so a larger seed would silently wrap onto a small one."""
    value = int_at_least(0, "non-negative", maximum=2**63)(text)  # past MAX_SEED: said below, as a seed's range
    if value > MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected a seed in [0, {MAX_SEED}], got {value}")
    return value


def fps(text: str) -> float:
    """Frames (or environment steps) per second: a number in (0, 100]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected frames per second (a number), got {text!r}") from None
    if not 0 < value <= 100:
        raise argparse.ArgumentTypeError(f"fps must be > 0 and <= 100, got {text}")
    return value


def add_set_option(parser: argparse.ArgumentParser, help: str) -> None:
    """Declare ``--set SECTION.KEY=VALUE`` (repeatable) on ``parser``: a config override that
    ``population.config.load_config`` applies, collected in ``args.overrides`` (a list, empty by
    default); ``help`` says what it overrides in this command."""
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE", help=help)


def checkpoint_choice(text: str, choices: Sequence[str]) -> str:
    """``text`` if it names a checkpoint (one of ``choices``, e.g. ``population.policy.CHECKPOINT_CHOICES``,
    or an update number), else a ``CLIError`` that lists them."""
    if text in choices or is_update_number(text):
        return text
    raise CLIError(f"--checkpoint: expected one of {', '.join(choices)} or an update number, got {text!r}")


def add_published_population(parser: argparse.ArgumentParser, default_folder: Path, pairs: bool = False) -> None:
    """The options of a results script that plays a published population (``<policies>/<method>_seed<i>_update<U>``
    files): --update, --episodes, --seeds, --method, --policies; ``published_files`` names the files they pick.
    With ``pairs``, also --pairs i,j ... (cross-play pairs: seat 0's seed, seat 1's), checked by
    ``published_pairs``."""
    parser.add_argument(
        "--update", type=non_negative_int, required=True, help="the snapshot (<method>_seed<i>_update<U>)"
    )
    parser.add_argument("--episodes", type=positive_int, default=32)
    parser.add_argument("--seeds", type=positive_int, default=10)
    parser.add_argument("--method", default="sp", help="the file names' method prefix (sp, sa, ...)")
    parser.add_argument("--policies", type=Path, default=default_folder, help="a published policies folder")
    if pairs:
        parser.add_argument("--pairs", type=seed_pair, nargs="*", default=[], help="cross-play pairs i,j to read too")


def seed_pair(text: str) -> tuple[int, int]:
    """argparse type: ``i,j`` (seat 0's seed, seat 1's seed)."""
    try:
        first, second = (int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected two seeds as i,j (seat 0's, seat 1's)") from None
    if min(first, second) < 0 or max(first, second) > MAX_INT:
        raise argparse.ArgumentTypeError(f"{text!r}: seeds are 0 or more, below 2**31")
    return first, second


def published_pairs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[tuple[int, int]]:
    """--pairs, each seed below --seeds (else the usage error that names the pair, before anything is played)."""
    for pair in args.pairs:
        if max(pair) >= args.seeds:
            parser.error(f"--pairs {pair[0]},{pair[1]}: seeds are 0 to {args.seeds - 1} (--seeds {args.seeds})")
    return list(args.pairs)


def published_files(args: argparse.Namespace) -> list[Path]:
    """The policy files the options of ``add_published_population`` pick, seed by seed."""
    return [args.policies / f"{args.method}_seed{seed}_update{args.update}.ocv2policy" for seed in range(args.seeds)]


def add_gif_options(parser: argparse.ArgumentParser) -> None:
    """The options of every command that writes one episode to a GIF (``render``, ``archive replay``): --out,
    --force, --fps, --view-radius and --tile-size, each checked by its type."""
    parser.add_argument("--out", required=True, help="GIF file to write (a new one unless --force)")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")
    parser.add_argument("--fps", type=fps, default=5.0, help="frames per second (default 5)")
    parser.add_argument(
        "--view-radius",
        type=non_negative_int,
        default=None,
        help="highlight every cell within this radius of an agent (default: none)",
    )
    parser.add_argument("--tile-size", type=positive_int, default=32, help="pixels per cell (default 32)")

"""``ocv2 archive``: inspect, replay and recover MCAP trajectory archives (``docs/archive.md``).

ocv2 archive info FILE [--limit N] [--json]
ocv2 archive replay FILE --episode N --out EPISODE.gif [--fps F] [--tile-size T] [--view-radius V]
ocv2 archive recover FILE [--out FIXED.mcap] [--force]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from cluster.archive import PARTIAL_SUFFIX, ArchiveError, ArchiveReader, recover
from cluster.cli.args import add_gif_options, check_new_file, check_not_under_a_file, int_at_least, non_negative_int
from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from ocv2.render import check_frame_size, render_frames, write_gif


def add_parser(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 archive`` and its actions (info, replay, recover) on ``sub`` (argparse
    subparsers); returns its parser."""
    parser = sub.add_parser(
        "archive",
        help="inspect, replay or recover an MCAP trajectory archive",
        description="Work with the MCAP trajectory archives of a run (RUN_DIR/archive/*.mcap).",
    )
    actions = parser.add_subparsers(dest="archive_command", metavar="ACTION")
    actions.required = True

    info = actions.add_parser(
        "info",
        help="episodes, layouts, policies and returns of an archive",
        description="Summarise an archive: episodes, layouts, methods, policies, returns, "
        "size; then one line per episode. Works on unfinished (.partial) files.",
    )
    info.add_argument("file", help="archive (.mcap, or a .mcap.partial being written or left by a killed writer)")
    info.add_argument(
        "--limit",
        type=int_at_least(-1, "-1 (all) or larger"),
        default=50,
        metavar="N",
        help="list at most N episodes (default 50; 0 lists none, -1 all)",
    )
    info.add_argument("--json", action="store_true", help="print the summary and episode metadata as JSON")

    replay = actions.add_parser(
        "replay",
        help="render an archived episode to a GIF",
        description="Render every stored state of one episode (T + 1 frames for T transitions) to a looping GIF.",
    )
    replay.add_argument("file", help="archive file")
    replay.add_argument(
        "--episode",
        type=non_negative_int,
        default=0,
        metavar="N",
        help="episode number, as 'info' lists it in its # column (default 0)",
    )
    add_gif_options(replay)

    recover = actions.add_parser(
        "recover",
        help="rescue the complete episodes of a killed writer's file",
        description="Read FILE up to its first truncated or corrupt record and write "
        "every complete episode to a new, finished archive.",
    )
    recover.add_argument("file", help="damaged or unfinished archive (typically NAME.mcap.partial)")
    recover.add_argument(
        "--out", help="clean archive to write (default: FILE without '.partial', else NAME.recovered.mcap)"
    )
    recover.add_argument("--force", action="store_true", help="replace --out if it exists")
    return parser


def run(args) -> int:
    """Run the ``ocv2 archive`` action ``args.archive_command`` names. Returns ``EXIT_OK``; raises
    ``CLIError`` for an unreadable or damaged archive, a bad option or an output it cannot write."""
    return {"info": _info, "replay": _replay, "recover": _recover}[args.archive_command](args)


def _reader(path: str) -> ArchiveReader:
    """The archive, its damage (skipped chunks, lost episodes) warned about on stderr."""
    try:
        reader = ArchiveReader(path)
    except ArchiveError as error:
        raise CLIError(str(error)) from None
    except OSError as error:
        raise CLIError(f"cannot read {path!r}: {error}") from None
    _warn(path, reader.warnings)
    return reader


def _warn(path: str, warnings) -> None:
    for warning in warnings:
        print(f"warning: {path}: {warning}", file=sys.stderr)


def _info(args) -> int:
    reader = _reader(args.file)
    summary = reader.info()
    if not reader.has_header:  # empty, or cut inside its first bytes: "UNFINISHED, recover it" would mislead
        raise CLIError(
            f"{args.file}: no ocv2 header in its {summary['size_bytes']} bytes (not an archive, or its writer was "
            "killed before it wrote its header): there is nothing to read or recover"
        )
    metas = reader.episodes()
    shown = metas if args.limit < 0 else metas[: args.limit]
    if args.json:
        print(json.dumps({"summary": summary, "episodes": shown}, indent=2))
        return EXIT_OK
    state = "finished" if summary["finished"] else "UNFINISHED"
    per = summary["bytes_per_transition"]
    print(
        f"{args.file}: {state} ocv2 archive, {summary['episodes']} complete episode(s), "
        f"{summary['transitions']} transitions, {_size(summary['size_bytes'])}"
        + (f" ({per:.1f} B/transition)" if per else "")
    )
    if not summary["finished"]:
        dropped = summary["uncommitted_messages"]
        print(
            f"  the writer did not finish (killed, or still writing); {dropped} message(s) of an incomplete "
            f"episode are not counted. Rescue the rest with: ocv2 archive recover {args.file}"
        )
    print(f"layouts: {_counts(summary['layouts'])}")
    print(f"methods: {_counts(summary['methods'])}")
    print(f"policies: {_counts(summary['policies'])}")
    returns = summary["returns"]
    if returns:
        print(
            f"returns: mean {returns['mean']:.2f}, std {returns['std']:.2f}, min {returns['min']:.2f}, "
            f"max {returns['max']:.2f}"
        )
        if len(summary["returns_by_layout"]) > 1:
            for name, stats in summary["returns_by_layout"].items():
                print(f"  {name}: mean {stats['mean']:.2f} (min {stats['min']:.2f}, max {stats['max']:.2f})")
    print(
        f"channels: {', '.join(summary['topics'])}" + (" (Foxglove frames: yes)" if summary["foxglove_frames"] else "")
    )
    if shown:
        header = ("#", "layout", "steps", "return", "shaped", "method", "iter", "policies", "seed")
        rows = [
            (
                str(m["episode"]),
                m["layout"],
                str(m["steps"]),
                f"{m['return']:g}",
                "/".join(f"{v:g}" for v in m["shaped_return"]),
                _text(m.get("method")),
                _text(m.get("iteration")),
                _text(m.get("policies")),
                _text(m.get("seed")),
            )
            for m in shown
        ]
        widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
        for row in [header, *rows]:
            print("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip())
        if len(shown) < len(metas):
            print(f"... {len(metas) - len(shown)} more (--limit -1 lists all)")
    return EXIT_OK


def _replay(args) -> int:
    if not args.out.lower().endswith(".gif"):
        raise CLIError(f"--out must name a .gif file, got {args.out!r}")
    check_new_file("--out", args.out, force=args.force)
    reader = _reader(args.file)
    try:
        index = reader.position(args.episode)  # the stored number info lists, not the position in the file
        episode = reader.episode(index)
        layout = reader.layout(index)
    except ArchiveError as error:
        raise CLIError(str(error)) from None
    try:  # the frames of one GIF live in memory together: refused before anything is drawn
        check_frame_size(layout, args.tile_size, frames=len(episode.states.step))
    except ValueError as error:
        raise CLIError(f"--tile-size {args.tile_size}: {error}") from None
    frames = render_frames(episode.states, layout, agent_view_size=args.view_radius, tile_size=args.tile_size)
    folder = os.path.dirname(os.path.abspath(args.out))
    try:
        os.makedirs(folder, exist_ok=True)
        path = write_gif(frames, args.out, fps=args.fps)
    except OSError as error:
        raise CLIError(f"could not write {args.out!r}: {error}", EXIT_FAILURE) from None
    meta = episode.meta
    print(
        f"wrote {path}: {len(frames)} frames (episode {meta['episode']}: {meta['steps']} steps of {layout.name}, "
        f"return {meta['return']:g})"
    )
    return EXIT_OK


def _recover(args) -> int:
    out = args.out
    if out is None:
        if args.file.endswith(PARTIAL_SUFFIX):
            out = args.file[: -len(PARTIAL_SUFFIX)]
        else:
            stem = args.file[: -len(".mcap")] if args.file.endswith(".mcap") else args.file
            out = stem + ".recovered.mcap"
    check_not_under_a_file("--out", out)
    if os.path.exists(out) and not args.force:
        raise CLIError(f"{out!r} already exists; choose another --out or pass --force")
    try:
        report = recover(args.file, out, overwrite=args.force)
    except ArchiveError as error:
        raise CLIError(str(error)) from None
    except OSError as error:
        raise CLIError(f"could not recover {args.file!r} into {out!r}: {error}", EXIT_FAILURE) from None
    _warn(args.file, report.warnings)
    if report.source_finished and not report.warnings:
        print(f"{args.file} was a finished archive; copied its {report.episodes} episode(s) to {report.path}")
        return EXIT_OK
    dropped = (
        f"; dropped {report.dropped_messages} message(s) of an incomplete episode" if report.dropped_messages else ""
    )
    stop = f" (the file ends in: {report.tail_error})" if report.tail_error else ""
    print(
        f"recovered {report.episodes} complete episode(s), {report.transitions} transitions, into "
        f"{report.path}{dropped}{stop}"
    )
    return EXIT_OK


def _size(num: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if num < 1024 or unit == "GiB":
            return f"{num:.0f} {unit}" if unit == "B" else f"{num:.1f} {unit}"
        num /= 1024
    return f"{num} B"  # pragma: no cover


def _counts(counts: dict) -> str:
    return ", ".join(f"{name} ({n})" for name, n in counts.items()) or "-"


def _text(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, list):
        return " + ".join(str(v) for v in value)
    return str(value)

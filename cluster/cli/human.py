"""``ocv2 human``: the 2019 human-human Overcooked games as ocv2 archives, and a behaviour-cloned proxy.

    ocv2 human import SOURCE [--out DIR] [--splits train,test] [--layouts L ...] [--max-trials N] [--overwrite]
    ocv2 human proxy LAYOUT --source SOURCE [--out FILE [--force]] [--steps N] [--batch-size B] [--lr LR] [--seed S]

SOURCE is the ``overcooked_ai-1.1.0.tar.gz`` source distribution (``pip download --no-deps
--no-binary :all: overcooked-ai==1.1.0``), a folder holding its ``clean_*_trials.pickle`` or one
pickle. ``import`` writes ``DIR/human_<split>_<layout>.mcap`` (one kitchen per file, so each is a
state-augmentation archive) and ``DIR/reproduction.json``: how many recorded transitions ocv2's
dynamics reproduce exactly. ``proxy`` trains the BC human proxy (``population.bc``) and saves it,
by default at ``population.human.proxy_path(LAYOUT)``. See docs/human.md.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

import ocv2
from cluster.archive import ArchiveError, ArchiveWriter, env_meta
from cluster.cli.args import bounded, check_new_file, positive_int, seed
from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from cluster.runtime.rundir import strict_json
from ocv2.atomic import atomic_write
from population import bc, human

DEFAULT_OUT = os.path.join("runs", "human")


def add_parser(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 human`` and its subcommands (import, proxy) on ``sub`` (argparse subparsers);
    returns its parser."""
    parser = sub.add_parser(
        "human",
        help="2019 human-human trials: import as archives, train a BC human proxy",
        description="Convert the overcooked-ai 1.1.0 human-human trials into ocv2 archives "
        "(with a check of ocv2's rules against them), or behaviour-clone a human "
        "proxy policy from them (docs/human.md).",
    )
    commands = parser.add_subparsers(dest="human_command", metavar="{import,proxy}")
    commands.required = True
    imp = commands.add_parser("import", help="write the trials as MCAP archives + a dynamics reproduction report")
    imp.add_argument(
        "source", metavar="SOURCE", help="overcooked_ai-1.1.0.tar.gz, a folder with the pickles, or one pickle"
    )
    imp.add_argument("--out", metavar="DIR", default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    imp.add_argument(
        "--splits",
        metavar="S",
        default="train,test",
        type=_splits,
        help="comma-separated splits to import (default train,test)",
    )
    imp.add_argument(
        "--layouts",
        metavar="L",
        nargs="+",
        default=None,
        help="only these layouts (ocv2 or overcooked-ai names; default all five)",
    )
    imp.add_argument(
        "--max-trials",
        metavar="N",
        type=positive_int,
        default=None,
        help="import at most N games per split (a quick look)",
    )
    imp.add_argument("--overwrite", action="store_true", help="replace existing archives in DIR")

    proxy = commands.add_parser("proxy", help="behaviour-clone a human proxy on one layout")
    proxy.add_argument("layout", metavar="LAYOUT", help="ocv2 layout: " + ", ".join(human.LAYOUT_MAP.values()))
    proxy.add_argument("--source", metavar="SOURCE", required=True, help="as for `ocv2 human import`")
    proxy.add_argument(
        "--out",
        metavar="FILE",
        default=None,
        help="proxy file (default: the cache, population.human.proxy_path(LAYOUT))",
    )
    proxy.add_argument("--force", action="store_true", help="replace an existing --out file")
    defaults = bc.BCConfig()
    proxy.add_argument("--steps", metavar="N", type=positive_int, default=defaults.steps, help="optimizer steps")
    proxy.add_argument("--batch-size", metavar="B", type=positive_int, default=defaults.batch_size)
    proxy.add_argument(
        "--eval-every",
        metavar="K",
        type=positive_int,
        default=defaults.eval_every,
        help="held-out accuracy every K steps",
    )
    proxy.add_argument(
        "--lr",
        metavar="LR",
        type=bounded(float, 0, 1, "a learning rate in (0, 1]", low_open=True),
        default=defaults.learning_rate,
    )
    proxy.add_argument("--seed", metavar="S", type=seed, default=defaults.seed)
    proxy.add_argument(
        "--episodes",
        metavar="E",
        type=positive_int,
        default=defaults.selfplay_episodes,
        help="self-play episodes for the proxy's own return",
    )
    proxy.add_argument(
        "--max-trials",
        metavar="N",
        type=positive_int,
        default=None,
        help="use at most N games per split (a quick look)",
    )
    return parser


def _splits(text: str) -> tuple[str, ...]:
    names = tuple(s for s in text.split(",") if s)
    bad = [s for s in names if s not in human.SPLITS]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"splits must be among {', '.join(human.SPLITS)}, got {text!r}")
    return names


def _warn_once(message: str, _seen: set = set()) -> None:  # noqa: B006 -- the set is the memory of this process
    if message not in _seen:  # both splits come from one sdist: one warning for it
        _seen.add(message)
        print(f"warning: {message}", file=sys.stderr, flush=True)


def _load(source: str, split: str, layouts, max_trials) -> list[human.Trial]:
    try:
        frame = human.read_frame(source, split, warn=_warn_once)
        rows = human.rows_from_frame(frame, f"{source} ({split} split)")
        return human.trials_from_rows(rows, split, layouts, max_trials)
    except human.HumanDataError as error:
        raise CLIError(str(error), EXIT_FAILURE) from None


def run(args) -> int:
    """Run the ``ocv2 human`` subcommand ``args.human_command`` names (``run_import`` or ``run_proxy``)
    and return its exit code."""
    if args.human_command == "import":
        return run_import(args)
    return run_proxy(args)


def archive_name(split: str, layout: str) -> str:
    """The file name ``import`` gives the archive of one split's games on one layout."""
    return f"human_{split}_{layout}.mcap"


def write_trials(path: str, trials: list[human.Trial], overwrite: bool = False) -> int:
    """Write ``trials`` (one layout) as one archive; ocv2's shaped rewards fill the shaped channel."""
    with ArchiveWriter(path, overwrite=overwrite, step_ns=150_000_000) as writer:
        for trial in trials:
            steps = len(trial.actions)
            _, _, shaped = human.step_recorded(trial)
            meta = {
                **env_meta(ocv2.make(trial.layout, max_steps=steps)),
                "method": "human",
                "kind": "human-human",
                "human_seats": [0, 1],
                "source": f"overcooked-ai==1.1.0 {human.PICKLE_NAMES[trial.split]}",
                "split": trial.split,
                "source_layout": trial.source_layout,
                "worker": trial.worker,
                "recorded_score": float(trial.rewards.sum() / human.REWARD_SCALE),
                "reward_scale": human.REWARD_SCALE,
            }
            dones = np.zeros(steps, bool)
            dones[-1] = True
            writer.write_episode(meta, trial.states, trial.actions, trial.rewards, shaped, dones, layout=trial.layout)
    return len(trials)


def run_import(args) -> int:
    """Convert the trials of ``args.splits`` into one archive per split and layout in ``args.out`` and
    write ``reproduction.json`` there, checking every trial before writing anything. Returns ``EXIT_OK``;
    raises ``CLIError`` for unreadable data, an archive that exists without ``--overwrite`` or a failed
    write."""
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise CLIError(f"--out {args.out}: is a file; give a folder")
    # Convert and check everything first: a bad row stops the import before any archive (or --out) is made.
    loaded = {split: _load(args.source, split, args.layouts, args.max_trials) for split in args.splits}
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as error:
        raise CLIError(f"--out {args.out}: cannot create the folder ({error.strerror or error})") from None
    targets = []
    for split, trials in loaded.items():
        for layout in dict.fromkeys(t.layout for t in trials):
            path = os.path.join(args.out, archive_name(split, layout))
            if os.path.exists(path) and not args.overwrite:
                raise CLIError(f"{path} exists; pass --overwrite to replace it")
            if os.path.exists(path + ".partial") and not args.overwrite:
                raise CLIError(f"{path}.partial exists (an unfinished import); pass --overwrite to import again")
            targets.append((path, [t for t in trials if t.layout == layout]))
    report = {"source": os.fspath(args.source), "splits": {}}
    for split, trials in loaded.items():
        report["splits"][split] = {}
        for layout in dict.fromkeys(t.layout for t in trials):
            games = [t for t in trials if t.layout == layout]
            report["splits"][split][layout] = {
                **human.reproduce(games)._asdict(),
                "games": len(games),
                "events": human.rule_events(games),
            }
    try:
        for path, trials in targets:
            write_trials(path, trials, overwrite=args.overwrite)
            print(f"wrote {path}: {len(trials)} games, {sum(len(t.actions) for t in trials)} transitions")
    except (ArchiveError, OSError) as error:
        raise CLIError(f"could not write the archive: {error}", EXIT_FAILURE) from None
    report_path = atomic_write(os.path.join(args.out, "reproduction.json"), strict_json(report) + "\n")
    print(f"{'split':6} {'layout':18} {'transitions':>11} {'exact':>7}  mismatches by field")
    for split, layouts in report["splits"].items():
        for layout, r in layouts.items():
            fields = ", ".join(f"{k} {v}" for k, v in r["by_field"].items() if v) or "none"
            print(f"{split:6} {layout:18} {r['transitions']:>11} {r['exact']:>7}  {fields}")
    print(f"wrote {report_path}")
    return EXIT_OK


def run_proxy(args) -> int:
    """Behaviour-clone a human proxy on ``args.layout`` from the train split, score it on the test split
    and save it to ``args.out`` (default: the proxy cache). Returns ``EXIT_OK``; raises ``CLIError`` for a
    layout without human data, a bad setting, unreadable data or a failed write."""
    try:
        layout = ocv2.layouts.get_layout(args.layout).name
    except ValueError as error:
        raise CLIError(str(error)) from None
    if layout not in human.LAYOUT_MAP.values():
        raise CLIError(f"layout {layout!r} has no human data; choose one of {', '.join(human.LAYOUT_MAP.values())}")
    try:
        config = bc.BCConfig(
            steps=args.steps,
            batch_size=args.batch_size,
            learning_rate=args.lr,
            eval_every=min(args.eval_every, args.steps),
            seed=args.seed,
            selfplay_episodes=args.episodes,
        )
    except ValueError as error:
        raise CLIError(str(error)) from None
    out = args.out or human.proxy_path(layout)
    # Before the training, not after it: an existing file (another policy?) is replaced only with --force; the
    # cache, the default, is replaced as a cache is.
    check_new_file("--out", os.fspath(out), force=args.force or args.out is None)
    train = _load(args.source, "train", [layout], args.max_trials)
    test = _load(args.source, "test", [layout], args.max_trials)
    result = bc.train(
        config,
        train,
        test,
        log=lambda e: print(
            f"step {e['step']:>6}  loss {e['loss']:.4f}  held-out accuracy {e['test_accuracy']:.3f}", flush=True
        ),
    )
    try:
        path = bc.save_proxy(
            out,
            result,
            config,
            meta={"source": os.fspath(args.source), "train_games": len(train), "test_games": len(test)},
        )
    except OSError as error:
        raise CLIError(f"could not write {out}: {error}", EXIT_FAILURE) from None
    s = result.scores
    print(
        f"{layout}: held-out accuracy {s['test_accuracy']:.3f} (uniform {s['uniform_accuracy']:.3f}, majority "
        f"{s['majority_accuracy']:.3f}); which action when the person acted {s['test_accuracy_active']:.3f} "
        f"(uniform {s['active_uniform_accuracy']:.3f}, majority {s['active_majority_accuracy']:.3f}); "
        f"self-play return {s['selfplay_return']:.1f} over {s['selfplay_episodes']} episodes of "
        f"{s['selfplay_max_steps']} steps"
    )
    print(f"wrote {path}")
    return EXIT_OK

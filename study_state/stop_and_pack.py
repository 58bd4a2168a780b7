"""End of a session with a study still training: stop it after its chunk in flight, publish its new snapshot policies,
pack its resumable state here.

    python study_state/stop_and_pack.py STUDY_DIR [--policies docs/results/<study>/policies]

0. What could make the steps below fail is checked first, while the study still trains (study.json, the runs'
   configs, the policies folder's listing, the pack's folder); any problem stops the script before step 1.
1. SIGTERM to the ``ocv2 study run`` of STUDY_DIR (the process whose command line's --out is STUDY_DIR, read from
   /proc): like Ctrl-C, it finishes the chunk in flight, saves and exits (SIGKILL after ``--wait`` minutes, 10 by
   default; a kill loses at most that chunk). Not SIGINT: a run started in the background (``nohup ... &``) ignores
   it. A chunk's time depends on the CPU (5 Asymm. Advantages SA updates: 8 minutes on one 2-core machine, 27 on
   another): give ``--wait`` the log's last chunk time, or start the script just before a chunk ends.
2. ``ocv2 study pack --latest-only`` into study_state/<study name>/ (written beside it first, then swapped in; a
   damaged checkpoint stops it and the earlier pack stays). First, because the next session continues from it.
3. Every kept snapshot of every run's seeds not published yet is exported into ``--policies`` (default
   docs/results/<study name>/policies), with its sha256 and env steps in SHA256SUMS.json, as ``ocv2 study publish``
   does (``population.published``); files already listed there are left as they are.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

from cluster.runtime.rundir import DirLock
from cluster.study.pack import pack_study
from cluster.study.publish import publish_study, trained_runs
from cluster.study.runner import check_folder
from cluster.study.spec import StudyError
from population.checkpoints import CheckpointError
from population.config import ConfigError, load_config
from population.policy import PolicyError
from population.published import checked_listing

HERE = Path(__file__).resolve().parent


def out_folder(pid: int) -> Path | None:
    """The resolved ``--out`` of process ``pid``'s command line (relative to its working directory), if any.
    Read from /proc, argument by argument: a pattern match would also take ``--out <study>_pilot``."""
    try:
        argv = [a.decode(errors="replace") for a in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")]
        cwd = Path(os.readlink(f"/proc/{pid}/cwd"))
    except OSError:  # it ended meanwhile, or is another user's
        return None
    for index, arg in enumerate(argv):
        if arg == "--out" and index + 1 < len(argv):
            return (cwd / argv[index + 1]).resolve()
        if arg.startswith("--out="):
            return (cwd / arg.removeprefix("--out=")).resolve()
    return None


def running(study: Path) -> list[int]:
    """The processes whose command line has ``--out`` = ``study`` (resolved)."""
    # "--" first: pgrep would read a pattern that starts with "--out" as an option, fail, and find nothing.
    found = subprocess.run(["pgrep", "-f", "--", "--out"], capture_output=True, text=True)
    if found.returncode > 1:
        raise SystemExit(f"pgrep failed ({found.stderr.strip()}); nothing was packed")
    pids = [int(pid) for pid in found.stdout.split() if int(pid) != os.getpid()]
    return [pid for pid in pids if out_folder(pid) == study.resolve()]


def stop(study: Path, wait_s: float = 600.0) -> None:
    """SIGTERM to the study's processes; SIGKILL to those still running after ``wait_s`` seconds."""
    pids = running(study)
    if not pids:
        print(f"no `ocv2 study run ... --out {study}` is running")
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
            os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        if gone(study):
            return
        time.sleep(min(1.0, wait_s))
    for pid in running(study):
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    for _ in range(300):  # the pack is refused while the study's lock is held
        if gone(study):
            return
        time.sleep(0.1)
    raise SystemExit(f"the study in {study} is still running after SIGKILL; nothing was packed")


def gone(study: Path) -> bool:
    """No process runs the study and none holds its lock: a killed process leaves /proc (its command line) a few
    milliseconds before the kernel closes its files, which is what lets the lock go."""
    return not running(study) and not DirLock(study).held_elsewhere()


def check_before_stopping(study: Path, policies: Path | None, into: Path) -> tuple[str, Path]:
    """Everything that would make the publish or the pack fail, checked while the study still trains: the
    study.json, each run's config, the policies folder and its listing, the pack's folder. Returns the study's
    name and its policies folder (``policies``, or docs/results/<name>/policies)."""
    name, runs = trained_runs(study)
    policies = policies or HERE.parent / "docs" / "results" / name / "policies"
    for run_dir in runs:
        load_config(run_dir / "config.yaml")
    checked_listing(policies)
    check_folder(into / name, "the pack's folder (--into)")
    return name, policies


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("study", type=Path, help="the study directory (ocv2 study run --out)")
    parser.add_argument("--policies", type=Path, help="where the policies go (default docs/results/<study>/policies)")
    parser.add_argument(
        "--into", type=Path, default=HERE, help="where the pack goes, as <study>/ (default study_state/)"
    )
    parser.add_argument(
        "--wait",
        type=float,
        default=10.0,
        help="minutes to let the chunk in flight finish before SIGKILL, which loses it (default 10)",
    )
    args = parser.parse_args()
    study = args.study.resolve()
    failures = (StudyError, ConfigError, PolicyError, CheckpointError, OSError)
    try:
        name, dest = check_before_stopping(study, args.policies, args.into)
    except failures as error:
        raise SystemExit(f"{error}\nnothing was stopped, published or packed") from None
    if not args.wait > 0:
        parser.error(f"--wait {args.wait:g}: minutes, more than 0")
    stop(study, args.wait * 60)
    # The pack first: it is what the next session continues from, and needs only the newest update every seed of a run has
    # (and the snapshots a later step reads, checked like it); a damaged older snapshot that no step reads must not
    # cost it (it stops only the publishing below).
    target, fresh, old = (args.into / f"{name}{suffix}" for suffix in ("", ".new", ".old"))
    try:
        shutil.rmtree(fresh, ignore_errors=True)
        record = pack_study(study, fresh, latest_only=True)
        shutil.rmtree(old, ignore_errors=True)
        if target.exists():
            target.rename(old)  # kept until the new pack is in place
        fresh.rename(target)
        shutil.rmtree(old, ignore_errors=True)
    except failures as error:
        raise SystemExit(
            f"{error}\nthe study was stopped; nothing was published, and {target} is as it was (or, if a rename "
            f"failed, in {old}): fix the cause and run this again"
        ) from None
    print(f"packed {record['bytes']:,} bytes in {len(record['parts'])} part(s) into {target}")
    try:
        for run_name, added in publish_study(study, dest)[1].items():
            print(f"{run_name}: {len(added)} policies exported into {dest}")
    except failures as error:
        raise SystemExit(
            f"{error}\nthe study was stopped and packed, but its snapshots were not all published"
        ) from None


if __name__ == "__main__":
    main()

"""End of a session with a study still training: stop it after its chunk in flight, publish its new snapshot policies,
pack its resumable state here.

    python study_state/stop_and_pack.py STUDY_DIR [--policies docs/results/<study>/policies]

1. SIGINT to the ``ocv2 study run`` of STUDY_DIR (found by its --out): it finishes the chunk in flight, saves and
   exits (SIGKILL after 10 minutes; a kill loses at most that chunk).
2. Every kept snapshot of every run's seeds not published yet is exported into ``--policies`` (default
   docs/results/<study name>/policies), with its sha256 and env steps in SHA256SUMS.json, as ``ocv2 study publish``
   does (``population.published``); files already listed there are left as they are.
3. ``ocv2 study pack --latest-only`` into study_state/<study name>/ (written beside it first, then swapped in).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

from cluster.study.pack import pack_study
from cluster.study.publish import publish_study, trained_runs
from cluster.study.spec import StudyError

HERE = Path(__file__).resolve().parent


def stop(study: Path) -> None:
    def running() -> list[str]:
        # "--" first: pgrep would read a pattern that starts with "--out" as an option, fail, and find nothing.
        found = subprocess.run(["pgrep", "-f", "--", f"--out {study}"], capture_output=True, text=True)
        if found.returncode > 1:
            raise SystemExit(f"pgrep failed ({found.stderr.strip()}); nothing was stopped or packed")
        return [pid for pid in found.stdout.split() if int(pid) != os.getpid()]

    pids = running()
    if not pids:
        print(f"no `ocv2 study run ... --out {study}` is running (started with another spelling of the path?)")
    for pid in pids:
        os.kill(int(pid), signal.SIGINT)
    for _ in range(600):
        if not running():
            return
        time.sleep(1)
    for pid in running():
        os.kill(int(pid), signal.SIGKILL)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("study", type=Path, help="the study directory (ocv2 study run --out)")
    parser.add_argument("--policies", type=Path, help="where the policies go (default docs/results/<study>/policies)")
    parser.add_argument(
        "--into", type=Path, default=HERE, help="where the pack goes, as <study>/ (default study_state/)"
    )
    args = parser.parse_args()
    study = args.study.resolve()
    try:
        name, _ = trained_runs(study)  # before anything is stopped
    except StudyError as error:
        raise SystemExit(str(error)) from None
    stop(study)
    dest = args.policies or HERE.parent / "docs" / "results" / name / "policies"
    for run_name, added in publish_study(study, dest)[1].items():
        print(f"{run_name}: {len(added)} policies exported into {dest}")
    target, fresh = args.into / name, args.into / f"{name}.new"
    shutil.rmtree(fresh, ignore_errors=True)
    record = pack_study(study, fresh, latest_only=True)
    shutil.rmtree(target, ignore_errors=True)
    fresh.rename(target)
    print(f"packed {record['bytes']:,} bytes in {len(record['parts'])} part(s) into {target}")


if __name__ == "__main__":
    main()

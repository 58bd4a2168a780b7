"""End of a session with a study still training: stop it after its chunk in flight, publish its new snapshot policies,
pack its resumable state here.

    python study_state/stop_and_pack.py STUDY_DIR [--policies docs/results/<study>/policies]

1. SIGINT to the ``ocv2 study run`` of STUDY_DIR (found by its --out): it finishes the chunk in flight, saves and
   exits (SIGKILL after 10 minutes; a kill loses at most that chunk).
2. Every kept snapshot of every run's seeds not published yet is exported (``ocv2 export``) into ``--policies``
   (default docs/results/<study name>/policies), with its sha256 and env steps in SHA256SUMS.json; files already
   listed there are left as they are.
3. ``ocv2 study pack --latest-only`` into study_state/<study name>/ (written beside it first, then swapped in).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

from cluster.study.pack import pack_study
from cluster.study.runner import read_state
from population import checkpoints as ckpt
from population.config import load_config
from population.policy import export_checkpoint

HERE = Path(__file__).resolve().parent


def stop(study: Path) -> None:
    def running() -> list[str]:
        found = subprocess.run(["pgrep", "-f", f"--out {study}"], capture_output=True, text=True).stdout.split()
        return [pid for pid in found if int(pid) != os.getpid()]

    pids = running()
    for pid in pids:
        os.kill(int(pid), signal.SIGINT)
    for _ in range(600):
        if not running():
            return
        time.sleep(1)
    for pid in running():
        os.kill(int(pid), signal.SIGKILL)


def publish(run: Path, dest: Path) -> int:
    config = load_config(run / "config.yaml")
    snapshots = set(ckpt.snapshot_updates(config.ppo.num_updates, config.run.num_checkpoints))
    dest.mkdir(parents=True, exist_ok=True)
    listed = dest / "SHA256SUMS.json"
    listing = json.loads(listed.read_text()) if listed.is_file() else []
    known = {entry["file"] for entry in listing}
    added = 0
    for seed in range(config.population.num_seeds):
        for update in ckpt.list_updates(run, seed):
            path = dest / f"{run.name}_seed{seed}_update{update}.ocv2policy"
            if update == 0 or update not in snapshots or path.name in known:
                continue
            export_checkpoint(run, path, seed=seed, checkpoint=update)
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
            steps = update * config.ppo.steps_per_update
            listing.append({"file": path.name, "seed": seed, "update": update, "env_steps": steps, "sha256": digest})
            added += 1
    listing.sort(key=lambda entry: (entry["update"], entry["seed"], entry["file"]))
    listed.write_text(json.dumps(listing, indent=1) + "\n")
    return added


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("study", type=Path, help="the study directory (ocv2 study run --out)")
    parser.add_argument("--policies", type=Path, help="where the policies go (default docs/results/<study>/policies)")
    parser.add_argument(
        "--into", type=Path, default=HERE, help="where the pack goes, as <study>/ (default study_state/)"
    )
    args = parser.parse_args()
    study = args.study.resolve()
    name = read_state(study).study
    stop(study)
    dest = args.policies or HERE.parent / "docs" / "results" / name / "policies"
    for run in sorted((study / "runs").iterdir()):
        if (run / "config.yaml").is_file():
            print(f"{run.name}: {publish(run, dest)} policies exported into {dest}")
    target, fresh = args.into / name, args.into / f"{name}.new"
    shutil.rmtree(fresh, ignore_errors=True)
    record = pack_study(study, fresh, latest_only=True)
    shutil.rmtree(target, ignore_errors=True)
    fresh.rename(target)
    print(f"packed {record['bytes']:,} bytes in {len(record['parts'])} part(s) into {target}")


if __name__ == "__main__":
    main()

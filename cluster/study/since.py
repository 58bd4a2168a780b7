"""What an extension changed: each run's seeds at the old stop beside the same seeds trained on.

A study extended with ``--extend`` trains every run on along the same schedule; the run's cross-play at the
old stop is kept in ``runs/<run>/extended/update_<n>/xp/`` (``cluster.runtime.extend``). Row k of both
matrices is seed k, so the change of SP, XP and gap gets the paired interval (``population.xp.paired_difference``:
one draw of seeds used in both matrices), narrower than two populations' and honest about what it compares.
"""

from __future__ import annotations

from pathlib import Path

from cluster.runtime.rundir import RunDir, RunDirError, float_or_nan, read_matrix_csv
from cluster.study.results import read_result
from cluster.study.spec import Study, run_dir
from population.xp import paired_difference

#: The numbers an entry holds for the old stop and the new one, and the name of each one's change.
KEYS = {"sp_mean": "sp", "xp_mean": "xp", "gap": "gap"}


def since_extension(study: Study, out: Path, runs: list[dict], configs: dict) -> list[dict]:
    """One entry per run and kept old stop, oldest first: the update and env steps per seed then and now, SP,
    XP and gap at both, their changes and the changes' 95 % paired intervals. An entry whose numbers cannot
    be read says why in ``problem`` (no cross-play at the new stop yet, a matrix cut or gone) instead of
    leaving the run out."""
    entries = []
    for spec, now in zip(study.runs, runs, strict=True):
        path = run_dir(out, spec.name)
        try:
            records = RunDir(path).read_manifest().get("extensions", []) if (path / "config.yaml").is_file() else []
        except RunDirError:  # the run's own entry says so already
            continue
        per_update = configs[spec.name].ppo.steps_per_update
        for record in sorted(records, key=lambda r: r["from_updates"]):
            old = record["from_updates"]
            entry = {
                "run": spec.name,
                "from_update": old,
                "from_env_steps_per_seed": old * per_update,
                "env_steps_per_seed": now["env_steps_per_seed"],
            }
            entries.append({**entry, **_compare(path / "extended" / f"update_{old:07d}" / "xp", path / "xp", now)})
    return entries


def _compare(before_dir: Path, after_dir: Path, now: dict) -> dict:
    """The numbers of one run at the old stop (``before_dir``) and the new one (``now``, its report entry)."""
    read, problem = read_result(before_dir / "summary.json", tuple(KEYS))
    if problem is not None:
        return {"problem": problem}
    entry = {"before": {key: float_or_nan(read[key]) for key in KEYS}}
    if now["xp"] is None or now.get("problem"):
        return entry | {"problem": now.get("problem") or "no cross-play at the new stop yet"}
    entry["after"] = {key: float_or_nan(now["xp"][key]) for key in KEYS}
    entry |= {f"delta_{name}": entry["after"][key] - entry["before"][key] for key, name in KEYS.items()}
    try:
        files = [folder / "matrix.csv" for folder in (before_dir, after_dir)]
        intervals = paired_difference(*[read_matrix_csv(f).values for f in files], names=tuple(map(str, files)))
    except (OSError, ValueError) as error:  # a matrix gone, cut or holed since its summary was written
        return entry | {"problem": f"no interval: {error}"}
    return entry | {f"delta_{name}_ci95_interval": list(intervals[name]) for name in KEYS.values()}

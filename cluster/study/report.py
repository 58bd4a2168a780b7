"""The study report: our numbers beside the paper's, per run and per comparison, with pictures.

``STUDY_DIR/report.md`` (for people), ``STUDY_DIR/summary.json`` (strict JSON: NaN is written as null),
``curves_<layout>.png`` (training curves of every run, mean ± std across seeds),
``heatmap_<run>.png`` (a run's seeds' final cross-play, as the paper's Figure 4),
``heatmap_<comparison>.png`` (the full cross-play matrix of a comparison) and
``over_training_<run>.png`` (SP, XP and the gap at every kept snapshot). A run of another method on the
same environment as a self-play run of the study is compared with it: Δ SP, Δ XP and Δ gap (Table 1's
bracket), the last with its own interval (both populations' seeds resampled, each on its own).

Every interval is a 95 % percentile bootstrap over training seeds. "paper in CI" says whether the
paper's mean lies inside our interval: a plain check, not a test of the paper's claim.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from pathlib import Path

import numpy as np

from cluster.runtime.crossplay import seat_pairs
from cluster.runtime.progress import duration
from cluster.runtime.rundir import RunDir, RunDirError, float_or_nan, read_matrix_csv, seed_curves, write_json
from cluster.study.results import compared_settings, config_differences, evaluation_problem, read_result
from cluster.study.since import KEYS, since_extension
from cluster.study.spec import PaperValue, Study, StudyError, comparison_dir, run_config, run_dir
from cluster.study.state import StepRecord, StudyState
from ocv2 import boundedjson
from ocv2.atomic import atomic_write
from population.config import METHOD_TABLE, ConfigError, load_config
from population.config.paper import PAPER_CONFIGS
from population.plots import PlotsUnavailable, pyplot, save_figure, skipped, xp_heatmap
from population.policy import comparable_key
from population.xp import summary_difference

METHOD_NAMES = {method.name: method.long_name for method in METHOD_TABLE}


def backends(state: StudyState) -> str | None:
    """The backend the study's steps ran on ("local"), or each with its steps when they ran on several
    ("ray (train sp), local (train sa, compare sp_vs_sa)"); steps recorded before steps named their backend
    count as ``state.backend``'s."""
    ran: dict[str, list[str]] = {}
    for name, step in state.steps.items():
        backend = step.backend or state.backend
        if backend is not None and step.done:  # what made the reported results
            ran.setdefault(backend, []).append(name)
    if len(ran) <= 1:
        return next(iter(ran), state.backend)
    return ", ".join(f"{backend} ({', '.join(names)})" for backend, names in ran.items())


def write_report(study: Study, out: Path, state: StudyState, configs: dict, dest: Path | None = None) -> dict:
    """The report of study directory ``out``, written into ``dest`` (default ``out``). Into another
    folder it comes with copies of the cross-play matrices (``xp_<run>.csv``, ``xp_<comparison>.csv``),
    which makes a compact, self-contained record without checkpoints or archives."""
    dest = out if dest is None else Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    if dest != out:
        _copy_matrices(study, out, dest)
    runs = [_run_entry(study, run, out, configs[run.name], state) for run in study.runs]
    comparisons = [_comparison_entry(c.name, out, state) for c in study.comparisons]
    over = [_over_training_entry(name, out) for name in study.over_training]
    summary = {
        "study": study.name,
        "source": str(study.path),
        "budget": state.budget,
        "budget_mode": state.budget_mode,
        "seeds": state.seeds,
        "set": list(state.overrides),
        "backend": backends(state),
        "written": _now(),
        "runs": runs,
        "comparisons": comparisons,
        "over_training": over,
        "against_sp": _against_sp(study, out, configs, runs),
        "ci_method": "95% percentile bootstrap over training seeds",
        "wall_s": round(sum(step.wall_s for step in state.steps.values()), 1),
    }
    if state.extensions:  # only then: a study never extended keeps the summary it always had
        summary["extensions"] = [{"from": e["from"], "to": e["to"]} for e in state.extensions]
        summary["since_extension"] = since_extension(study, out, runs, configs)
    pictures = (
        _curves(study, out, configs, dest) + _heatmaps(out, runs, comparisons, dest) + _over_training_plots(dest, over)
    )
    summary["pictures"] = [Path(p).name for p in pictures]
    write_json(dest / "summary.json", summary)  # strict JSON: NaN as null
    atomic_write(dest / "report.md", markdown(study, summary, state, experiment=as_written(study, out, state)))
    return {"report": str(dest / "report.md"), "summary": str(dest / "summary.json")}


def damaged(summary: dict) -> list[str]:
    """The steps whose results the report (its ``summary``) could not use (a cross-play summary missing or
    unreadable, a run directory gone): report.md lists them under "Not finished" and ``ocv2 study report`` says
    them on stderr."""
    found = [f"train {run['name']}: {run['problem']}" for run in summary["runs"] if run.get("problem")]
    found += [
        f"over_training {e['run']}: {problem}" for e in summary["over_training"] for problem in e.get("damaged", [])
    ]
    return found + [f"compare {c['name']}: {c['reason']}" for c in summary["comparisons"] if c["status"] == "damaged"]


def _copy_matrices(study: Study, out: Path, dest: Path) -> None:
    sources = [(run_dir(out, r.name) / "xp" / "matrix.csv", f"xp_{r.name}.csv") for r in study.runs]
    sources += [(comparison_dir(out, c.name) / "matrix.csv", f"xp_{c.name}.csv") for c in study.comparisons]
    for source, name in sources:
        if source.is_file():
            atomic_write(dest / name, source.read_text())


# ---------------------------------------------------------------------------------------------------
# collecting
# ---------------------------------------------------------------------------------------------------


#: Compared settings a study may change and still run its configs' experiment: they make GPU ops reproducible,
#: not other numbers. Neither are the cluster, archive and checkpoint-cadence keys (``compared_settings``).
_NOT_AN_EXPERIMENT_CHANGE = ("run.deterministic",)


def as_written(study: Study, out: Path, state: StudyState) -> tuple[bool, str]:
    """Whether every run trains its config file's experiment as written (its training settings, seeds and
    evaluation episodes; the budget aside, which report.md names itself), and each change the study file's ``set``,
    ``--set``, ``--seeds`` or ``partners_from`` makes to them, in brief, for report.md ("the study changes its
    configs: `eval.episodes=2`, `ppo.lr (sa)`": a key set to one value in every run, or the runs that change it).
    (False, why) when a config no longer loads."""
    changed: dict[str, dict[str, object]] = {}
    for run in study.runs:
        try:
            written = compared_settings(load_config(run.config))
            planned = compared_settings(run_config(study, run, out, 1.0, state.seeds, state.budget_mode))
        except (ConfigError, StudyError):  # it loaded at the study's budget: hardly ever
            return False, f"run {run.name}'s config does not load as written"
        for key in sorted(set(written) | set(planned)):
            if key not in _NOT_AN_EXPERIMENT_CHANGE and written.get(key) != planned.get(key):
                changed.setdefault(key, {})[run.name] = planned.get(key)
    if not changed:
        return True, ""
    items = [f"`{item}`" for item in _brief_changes(changed, [run.name for run in study.runs])]
    return False, "the study changes its configs: " + ", ".join(items[:6]) + (
        f" and {len(items) - 6} more" if len(items) > 6 else ""
    )


def _brief_changes(changed: dict[str, dict[str, object]], runs: list[str]) -> list[str]:
    """``changed`` (key -> run -> value) as a few items: a key whose siblings changed too as ``parent.*`` (an FCP
    run's partner_ppo section), a key of one value as ``key=value``, the runs it concerns when not all."""
    parents: dict[str, list[str]] = {}
    for key in changed:
        parents.setdefault(key.rpartition(".")[0], []).append(key)
    items, seen = [], set()
    for key, values in changed.items():
        parent = key.rpartition(".")[0]
        if len(parents[parent]) > 3:
            if parent in seen:
                continue
            seen.add(parent)
            names = sorted({run for sibling in parents[parent] for run in changed[sibling]}, key=runs.index)
            text = f"{parent}.*"
        else:
            names = list(values)
            shown = {repr(v) for v in values.values()}
            value = next(iter(values.values()))
            text = f"{key}={_plain(value)}" if len(shown) == 1 else key
        items.append(text + ("" if len(names) == len(runs) else f" ({', '.join(names)})"))
    return items


def _plain(value) -> str:
    """A value as an override writes it (``true``, ``[8, 8]``)."""
    text = value if isinstance(value, str) else json.dumps(value, default=str)
    return text if len(text) <= 30 else text[:27] + "..."


def _paper_configs(study: Study) -> bool:
    """Whether every run's config file is one of the paper's (``configs/paper/``)."""
    paper = Path(str(PAPER_CONFIGS)).resolve()
    return all(Path(run.config).resolve().parent == paper for run in study.runs)


def _described(config) -> dict:
    """What the report says of a run's config: method, layout, model, seeds, env steps per seed, fingerprint."""
    return {
        "method": config.population.method,
        "layout": config.env_kwargs["layout"],
        "model": config.model.kind,
        "seeds": config.population.num_seeds,
        "env_steps_per_seed": config.ppo.num_updates * config.ppo.steps_per_update,
        "fingerprint": config.fingerprint(),
    }


def _run_entry(study: Study, spec, out: Path, config, state: StudyState) -> dict:
    path = run_dir(out, spec.name)
    step = state.steps.get(f"train {spec.name}", StepRecord())
    entry = {
        "name": spec.name,
        "config": str(spec.config),
        "overrides": list(spec.overrides),
        **_described(config),
        "status": "not started",
        "wall_s": step.wall_s if f"train {spec.name}" in state.steps else None,
        "commits": [],
        "versions": [],
        "xp": None,
        "paper": None
        if spec.paper is None
        else {
            "source": spec.paper.source,
            "note": spec.paper.note,
            **{k: _paper(getattr(spec.paper, k)) for k in ("sp", "xp", "gap")},
        },
    }
    if not (path / "config.yaml").is_file():
        # study.json says it trained: its directory went missing. Otherwise it is only "not started".
        if step.recorded_progress:
            entry["status"] = "damaged"
            entry["problem"] = f"{path}: missing, though study.json records the step as {step.status}"
        return entry
    run = RunDir(path)
    try:
        manifest = run.read_manifest()
        trained = run.load_config()
    except RunDirError as error:
        entry["status"] = "damaged"
        entry["problem"] = str(error)
        return entry
    # The run as it was trained, not as the study's files say today (a config changed since: `run` refuses it).
    entry.update(_described(trained))
    changed = config_differences(trained, config)
    if changed:
        entry["config_changed"] = changed
    entry["status"] = manifest.get("status", "created")
    entry["update"] = manifest.get("update")
    drivers = _drivers(path)
    entry["commits"] = _commits(drivers)
    entry["versions"] = _versions(drivers)
    summary_path = path / "xp" / "summary.json"
    if summary_path.is_file():
        xp, problem = read_result(summary_path, ("sp_mean", "xp_mean"))
        if problem is None:  # e.g. redone by `ocv2 xp RUN --episodes N`: not the run's own numbers
            problem = evaluation_problem(summary_path, xp, trained)
        if problem is not None:  # reported, and `ocv2 study run` evaluates the run again
            entry["problem"] = problem
            return entry
        entry["xp"] = {
            key: xp.get(key)
            for key in (
                "sp_mean",
                "sp_std",
                "xp_mean",
                "xp_std",
                "gap",
                "sp_ci95_interval",
                "xp_ci95_interval",
                "gap_ci95_interval",
                "episodes_per_pair",
                "num_policies",
            )
        }
    return entry


def _against_sp(study: Study, out: Path, configs: dict, runs: list[dict]) -> list[dict]:
    """Each other evaluated run minus the first self-play run of the same game and network (``comparable_key``, as
    ``ocv2 report`` groups runs): Δ SP, Δ XP, Δ gap with the gap's 95 % interval from both runs' matrices, and the paper's Δ gap
    where both runs carry the paper's gap. A run whose self-play run has no usable cross-play yet gets an
    entry that says so, rather than no entry."""
    entries = {entry["name"]: entry for entry in runs}

    def usable(spec) -> bool:
        return entries[spec.name]["xp"] is not None and not entries[spec.name].get("problem")

    keys = {run.name: comparable_key(configs[run.name]) for run in study.runs}
    out_entries = []
    for spec in filter(usable, study.runs):
        sp_runs = (r for r in study.runs if configs[r.name].population.method == "sp")
        base = next((r for r in sp_runs if keys[r.name] == keys[spec.name]), None)
        if base is None or base is spec:
            continue
        if not usable(base):
            out_entries.append(
                {
                    "run": spec.name,
                    "sp_run": base.name,
                    "problem": f"self-play run {base.name} has no usable cross-play",
                }
            )
            continue
        names = (f"{base.name}'s", f"{spec.name}'s")
        try:
            matrices = [read_matrix_csv(run_dir(out, r.name) / "xp" / "matrix.csv").values for r in (base, spec)]
        except (OSError, ValueError) as error:  # a matrix gone or cut since its summary: said so
            matrices, read_problem = [None, None], str(error)
        else:
            read_problem = ""
        delta = summary_difference(entries[base.name]["xp"], entries[spec.name]["xp"], *matrices, names=names)
        problem = read_problem or delta.problem
        paper = [(entries[r.name]["paper"] or {}).get("gap") for r in (base, spec)]
        out_entries.append(
            {
                "run": spec.name,
                "sp_run": base.name,
                "delta_sp": delta.sp,
                "delta_xp": delta.xp,
                "delta_gap": delta.gap,
                "delta_gap_ci95_interval": list(delta.gap_interval),
                "paper_delta_gap": None if None in paper else paper[1]["mean"] - paper[0]["mean"],
                **({"problem": f"no interval: {problem}"} if problem else {}),
            }
        )
    return out_entries


def _paper(value: PaperValue | None) -> dict | None:
    return None if value is None else {"mean": value.mean, "std": value.std}


def _jax_versions(versions: list[dict]) -> str:
    """``; jax 0.10.2`` (each distinct version, in order) for report.md's line of a run; "" when none is known."""
    jax_versions = list(dict.fromkeys(str(v["jax"]) for v in versions if v.get("jax")))
    return f"; jax {', '.join(jax_versions)}" if jax_versions else ""


def _drivers(path: Path) -> list[dict]:
    """The records of every driver that trained the run (``environment.json``); [] when it cannot be read."""
    try:
        drivers = boundedjson.loads((path / "environment.json").read_text()).get("drivers", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [driver for driver in drivers if isinstance(driver, dict)] if isinstance(drivers, list) else []


def _commits(drivers: list[dict]) -> list[str]:
    """The drivers' commits, marked when their checkout had uncommitted changes (``environment.json`` names the
    changed files of the runs made since it records them)."""
    commits = []
    for driver in drivers:
        git = driver.get("git") or {}
        commit = git.get("commit") if isinstance(git, dict) else None
        label = (commit if isinstance(commit, str) else "unknown")[:10] + ("+dirty" if git.get("dirty") else "")
        if label not in commits:
            commits.append(label)
    return commits


#: The versions a run's summary entry records, of those ``environment.json`` holds: what decides its numbers.
VERSIONS = ("python", "jax", "jaxlib", "flax", "optax", "numpy")


def _versions(drivers: list[dict]) -> list[dict]:
    """The distinct ``VERSIONS`` the drivers ran with, in the order they first appear."""
    distinct = []
    for driver in drivers:
        versions = driver.get("versions")
        if isinstance(versions, dict):
            entry = {name: versions.get(name) for name in VERSIONS if name in versions}
            if entry and entry not in distinct:
                distinct.append(entry)
    return distinct


def _comparison_entry(name: str, out: Path, state: StudyState) -> dict:
    step = state.steps.get(f"compare {name}")
    entry = {
        "name": name,
        "status": "left" if step is None else step.status,
        "reason": "" if step is None else step.reason or "",
        "wall_s": None if step is None else step.wall_s,
    }
    path = comparison_dir(out, name) / "summary.json"
    if path.is_file():
        data, problem = read_result(path)
        pairs, blocks = _pairs_and_blocks(data) if problem is None else (None, None)
        if problem is None and not (isinstance(pairs, list) and all(_is_pair(p) for p in pairs)):
            problem = f"{path} holds no pairs of policies"
        if problem is not None:
            entry.update(status="damaged", reason=problem)
            return entry
        entry.update(pairs=pairs, blocks=blocks, episodes_per_pair=data.get("episodes_per_pair"))
    return entry


def _pairs_and_blocks(data: dict) -> tuple[list | None, list]:
    """A comparison's pairs (``crossplay.seat_pairs``) and its blocks with the rows in seat 0, from its
    summary.json: ``summarize_seat_fair``'s, or the ``pairs`` and ``blocks`` a study made before that kept.
    (None, []) when the file holds neither."""
    if "orders" in data:
        try:
            return seat_pairs(data), data["orders"]["rows_seat0"]
        except (KeyError, IndexError, TypeError):
            return None, []
    return data.get("pairs"), data.get("blocks", [])


_PAIR_KEYS = ("a", "b", "a_method", "b_method", "a_seat0", "a_seat0_std", "a_seat1", "a_seat1_std", "mean")


def _is_pair(pair) -> bool:
    return isinstance(pair, dict) and all(key in pair for key in (*_PAIR_KEYS, "mean_ci95_interval"))


_POINT_KEYS = ("update", "env_steps_per_seed", "sp_mean", "xp_mean", "gap")


def _is_point(point: dict) -> bool:
    """An over-training result the report and the plot can use: whole update and step numbers, means
    (null when undefined) and intervals of two numbers (or null)."""
    whole = all(isinstance(point[k], int) and not isinstance(point[k], bool) for k in _POINT_KEYS[:2])
    means = all(point[k] is None or _is_number(point[k]) for k in _POINT_KEYS[2:])
    intervals = all(
        point.get(f"{k}_ci95_interval") is None
        or (isinstance(point[f"{k}_ci95_interval"], list) and len(point[f"{k}_ci95_interval"]) == 2)
        for k in ("sp", "xp", "gap")
    )
    return whole and means and intervals


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _over_training_entry(name: str, out: Path) -> dict:
    folder = out / "over_training" / name
    points, damaged = [], []
    for path in sorted(folder.glob("update_*.json")):
        data, problem = read_result(path, _POINT_KEYS)
        if problem is None and not _is_point(data):
            problem = f"{path} holds values that are not numbers"
        if problem is None:
            points.append(data)
        else:
            damaged.append(problem)  # left out; `ocv2 study run` plays that snapshot again
    return {
        "damaged": damaged,
        "run": name,
        "points": [
            {
                k: p.get(k)
                for k in (
                    "update",
                    "env_steps_per_seed",
                    "sp_mean",
                    "xp_mean",
                    "gap",
                    "sp_ci95_interval",
                    "xp_ci95_interval",
                    "gap_ci95_interval",
                    "episodes_per_pair",
                    "matrix",
                )
            }
            for p in points
        ],
    }


# ---------------------------------------------------------------------------------------------------
# pictures
# ---------------------------------------------------------------------------------------------------


def _curves(study: Study, out: Path, configs: dict, dest: Path) -> list[str]:
    by_layout: dict = {}
    for spec in study.runs:
        path = run_dir(out, spec.name)
        if (path / "metrics.csv").is_file():
            by_layout.setdefault(configs[spec.name].env_kwargs["layout"], []).append((spec, path))
    pictures = []
    for layout, members in by_layout.items():
        target = dest / f"curves_{layout}.png"
        figure = _figure(target)
        if figure is None:
            return []
        plt, fig, ax = figure
        for spec, path in members:
            steps, mean, std = _curve(RunDir(path).read_metrics())
            if steps.size == 0:
                continue
            config = configs[spec.name]
            (line,) = ax.plot(
                steps,
                mean,
                label=f"{spec.name} ({config.population.method.upper()}, {config.population.num_seeds} seeds)",
            )
            ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        pictures.append(
            _finish(
                plt,
                fig,
                ax,
                target,
                "environment steps per seed",
                "sparse return (mean ± std across seeds)",
                f"{study.name}: {layout}",
            )
        )
    return pictures


def _figure(target: Path):
    """(pyplot, figure, axes) of a 6.5 x 4 inch line plot for ``target``; None when matplotlib is
    missing (``skipped`` says so, naming ``target``)."""
    try:
        plt = pyplot()
    except PlotsUnavailable as error:
        skipped(target, error)
        return None
    fig, ax = plt.subplots(figsize=(6.5, 4))
    return plt, fig, ax


def _finish(plt, fig, ax, target: Path, xlabel: str, ylabel: str, title: str) -> str:
    """Labels, grid and legend of a line plot; saves and closes it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:  # no labelled line (no episode finished yet): no empty legend
        ax.legend(loc="upper left", fontsize=8)
    path = save_figure(fig, target)
    plt.close(fig)
    return path


def _curve(rows: list[dict]):
    """(env steps per seed, mean, std) across the seeds that had a finished episode, per update where at
    least one had (``rundir.seed_curves``' sparse return)."""
    curves = seed_curves(rows)
    values = curves.values["sparse_return"]
    kept = ~np.isnan(values).all(axis=0) if values.size else np.zeros(0, bool)
    columns = [values[:, u][~np.isnan(values[:, u])] for u in np.flatnonzero(kept)]
    steps = np.asarray(curves.env_steps, np.float64)[kept] if kept.size else np.zeros(0)
    return steps, np.asarray([v.mean() for v in columns]), np.asarray([v.std() for v in columns])


def _heatmaps(out: Path, runs: list[dict], comparisons: list[dict], dest: Path) -> list[str]:
    """One heatmap per run (its seeds' final cross-play, the paper's Figure 4) and per comparison."""
    sources = [
        (run_dir(out, r["name"]) / "xp" / "matrix.csv", r["name"], "cross-play of its seeds (final)", r["xp"])
        for r in runs
        if r["xp"] is not None
    ]
    sources += [
        (comparison_dir(out, c["name"]) / "matrix.csv", c["name"], "cross-play", c)
        for c in comparisons
        if c.get("pairs")
    ]
    pictures = []
    for path, name, what, entry in sources:
        if not path.is_file():
            continue
        try:
            table = read_matrix_csv(path)
        except (OSError, ValueError):  # a damaged matrix: no picture (its step's summary says what is there)
            continue
        picture = xp_heatmap(
            table.values,
            dest / f"heatmap_{name}.png",
            labels=table.rows,
            col_labels=table.cols,
            title=f"{name}: {what}, {entry.get('episodes_per_pair')} episodes/pair",
        )
        if picture is not None:
            pictures.append(picture)
    return pictures


def _over_training_plots(dest: Path, over: list[dict]) -> list[str]:
    pictures = []
    for entry in over:
        points = entry["points"]
        if not points:
            continue
        target = dest / f"over_training_{entry['run']}.png"
        figure = _figure(target)
        if figure is None:
            return []
        plt, fig, ax = figure
        steps = np.asarray([p["env_steps_per_seed"] for p in points], np.float64)
        for key, label in (("sp", "SP (diagonal)"), ("xp", "XP (off-diagonal)"), ("gap", "gap SP - XP")):
            mean = np.asarray([float_or_nan(p[f"{key}_mean" if key != "gap" else "gap"]) for p in points])
            low = np.asarray([float_or_nan((p[f"{key}_ci95_interval"] or [None])[0]) for p in points])
            high = np.asarray([float_or_nan((p[f"{key}_ci95_interval"] or [None, None])[1]) for p in points])
            (line,) = ax.plot(steps, mean, marker="o", label=label)
            ax.fill_between(steps, low, high, color=line.get_color(), alpha=0.2)
        pictures.append(
            _finish(
                plt,
                fig,
                ax,
                target,
                "environment steps per seed (snapshot)",
                "team return (95 % seed-bootstrap interval)",
                f"{entry['run']}: cross-play of the kept snapshots",
            )
        )
    return pictures


# ---------------------------------------------------------------------------------------------------
# markdown
# ---------------------------------------------------------------------------------------------------


def markdown(study: Study, summary: dict, state: StudyState, experiment: tuple[bool, str] = (True, "")) -> str:
    """report.md's text: the header, our numbers beside the paper's per run, each comparison's seat
    orders, the over-training tables and the pictures, from ``summary`` (``write_report``'s), the
    study directory's ``state`` and ``experiment`` (``as_written``: whether the runs train their configs as
    written, and what the study changes)."""
    left = [
        f"- {name}: {step.status}" + (f" ({step.reason})" if step.reason else "")
        for name, step in state.steps.items()
        if not step.done
    ]
    lines = [f"# Study `{study.name}`", ""]
    if study.description:
        lines += [study.description, ""]
    budget, mode = summary["budget"], summary.get("budget_mode", "compress")
    how = {
        "truncate": "each config's schedule as written, stopped after that share of its steps (truncated)",
        "compress": "each config's whole schedule squeezed into that share of its steps (compressed)",
    }[mode]
    unchanged, changed = experiment
    if budget != 1:
        what = f" (**reduced: not the paper's experiment**; {how}" + (f"; {changed})" if changed else ")")
    elif not unchanged:
        what = f" (**reduced or changed: not the paper's experiment**; {changed})"
    else:
        what = " (the paper's experiment)" if _paper_configs(study) else " (the configs as written)"
    lines += [
        f"- study file: `{study.path.name}`; budget: **{budget:g} x** the configs' env steps{what}",
        *[
            f"- extended (`--extend`): trained first to budget {e['from']:g}, then on along the same schedules to "
            f"{e['to']:g}; the report and cross-play at {e['from']:g} are in `extended/budget_{e['from']:g}/`"
            for e in summary.get("extensions", [])
        ],
        f"- seeds per run: {summary['seeds'] or 'as each config'}; backend: {summary['backend']}; "
        f"wall time{' so far' if left else ''}: {duration(summary['wall_s'])}",
        *([f"- every run also with `{' '.join(summary['set'])}` (`--set`)"] if summary["set"] else []),
        f"- intervals: {summary['ci_method']}; 'in CI': the paper's mean lies inside our interval",
        f"- written {summary['written']}",
        "",
    ]
    lines += [
        "## Runs: ours beside the paper's",
        "",
        "| run | method | layout | seeds x env steps | SP ours [95% CI] | SP paper | XP ours [95% CI] | XP paper "
        "| gap ours [95% CI] | gap paper | paper source |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in summary["runs"]:
        xp, paper = run["xp"], run["paper"] or {}
        cells = [
            run["name"],
            METHOD_NAMES.get(run["method"], run["method"]),
            run["layout"],
            f"{run['seeds']} x {steps_text(run['env_steps_per_seed'])}",
        ]
        for key, mean_key in (("sp", "sp_mean"), ("xp", "xp_mean"), ("gap", "gap")):
            if xp is None:
                cells.append(f"n/a ({run.get('problem') or run['status']})")
            else:
                cells.append(_with_ci(xp.get(mean_key), xp.get(f"{key}_ci95_interval")))
            cells.append(_paper_cell(paper.get(key), None if xp is None else xp.get(f"{key}_ci95_interval")))
        cells.append(paper.get("source", "") + (f" ({paper['note']})" if paper.get("note") else ""))
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    lines += ["", "Per run: "]
    for run in summary["runs"]:
        lines.append(
            f"- `{run['name']}`: status {run['status']}, wall {duration(run['wall_s'])}, config "
            f"`{Path(run['config']).name}`"
            + (f" with `{' '.join(run['overrides'])}`" if run["overrides"] else "")
            + f", fingerprint `{run['fingerprint']}`, commits {', '.join(run['commits']) or 'n/a'}"
            + _jax_versions(run.get("versions") or [])
        )
    if summary["comparisons"]:
        lines += [
            "",
            "## Cross-play between runs (both seat orders)",
            "",
            "| comparison | A | B | A seat 0, B seat 1 | B seat 0, A seat 1 | mean of both [95% CI] |",
            "|---|---|---|---|---|---|",
        ]
        for entry in summary["comparisons"]:
            if not entry.get("pairs"):
                lines.append(
                    f"| {entry['name']} | | | n/a ({entry['status']}{': ' + entry['reason'] if entry['reason'] else ''}) | | |"
                )
                continue
            for pair in entry["pairs"]:
                lines.append(
                    f"| {entry['name']} | {_label(pair['a'], pair['a_method'])} | "
                    f"{_label(pair['b'], pair['b_method'])} | {_pm(pair['a_seat0'], pair['a_seat0_std'])} | "
                    f"{_pm(pair['a_seat1'], pair['a_seat1_std'])} | "
                    f"{_with_ci(pair['mean'], pair['mean_ci95_interval'])} |"
                )
    if summary.get("against_sp"):
        lines += [
            "",
            "## Against self-play (this run minus the self-play run of the same environment)",
            "",
            "Δ gap is the paper's Table 1 bracket; its interval resamples both runs' seeds, each on its own.",
            "",
            "| run | self-play run | Δ SP | Δ XP | Δ gap ours [95% CI] | Δ gap paper |",
            "|---|---|---|---|---|---|",
        ]
        for entry in summary["against_sp"]:
            if "delta_gap" not in entry:
                lines.append(f"| {entry['run']} | {entry['sp_run']} | n/a ({entry['problem']}) | | | |")
                continue
            paper = entry["paper_delta_gap"]
            lines.append(
                f"| {entry['run']} | {entry['sp_run']} | {_with_ci(entry['delta_sp'], None, signed=True)} | "
                f"{_with_ci(entry['delta_xp'], None, signed=True)} | "
                f"{_with_ci(entry['delta_gap'], entry['delta_gap_ci95_interval'], signed=True)}"
                f"{' (' + entry['problem'] + ')' if entry.get('problem') else ''} | "
                f"{'–' if paper is None else f'{paper:+g}'} |"
            )
    lines += since_extension_lines(summary.get("since_extension", []))
    for entry in summary["over_training"]:
        if not entry["points"]:
            continue
        lines += [
            "",
            f"## When does the gap open? `{entry['run']}`, cross-play of every kept snapshot",
            "",
            "| env steps per seed | SP [95% CI] | XP [95% CI] | gap [95% CI] |",
            "|---|---|---|---|",
        ]
        for p in entry["points"]:
            lines.append(
                f"| {steps_text(p['env_steps_per_seed'])} | {_with_ci(p['sp_mean'], p['sp_ci95_interval'])} | "
                f"{_with_ci(p['xp_mean'], p['xp_ci95_interval'])} | "
                f"{_with_ci(p['gap'], p['gap_ci95_interval'])} |"
            )
    if summary["pictures"]:
        lines += ["", "## Pictures", ""] + [f"![{name}]({name})" for name in summary["pictures"]]
    left += [f"- {line}" for line in damaged(summary)]
    left += [
        f"- train {run['name']}: its numbers are of the config it was trained with, not of the one the study asks "
        f"for now ({'; '.join(run['config_changed'])}); `ocv2 study run` refuses it until the change is undone or "
        f"--retrain {run['name']} trains it again"
        for run in summary["runs"]
        if run.get("config_changed")
    ]
    if left:
        lines += ["", "## Not finished", ""] + left
    return "\n".join(lines) + "\n"


def since_extension_lines(entries: list[dict]) -> list[str]:
    """report.md's table of what each extension changed (``cluster.study.since``), or nothing."""
    if not entries:
        return []
    lines = [
        "",
        "## Since the extension: the same seeds at the old stop and trained on",
        "",
        "Each Δ's interval resamples the seeds once and uses the draw at both stops (seed k is row k of both "
        "matrices).",
        "",
        "| run | env steps per seed | SP then → now | XP then → now | gap then → now | Δ SP [95% CI] | Δ XP [95% CI] "
        "| Δ gap [95% CI] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in entries:
        stops = f"{steps_text(e['from_env_steps_per_seed'])} → {steps_text(e['env_steps_per_seed'])}"
        if "after" not in e:
            lines.append(f"| {e['run']} | {stops} | n/a ({e['problem']}) | | | | | |")
            continue
        cells = [f"{_with_ci(e['before'][key], None)} → {_with_ci(e['after'][key], None)}" for key in KEYS]
        cells += [_with_ci(e[f"delta_{n}"], e.get(f"delta_{n}_ci95_interval"), signed=True) for n in KEYS.values()]
        note = f" ({e['problem']})" if e.get("problem") else ""
        lines.append(f"| {e['run']} | {stops} | " + " | ".join(cells) + note + " |")
    return lines


def steps_text(steps: int) -> str:
    """Env steps for a table: millions from 1M on ("30.00M"), below that exact ("65,536"; a pilot's 512
    steps are not "0.00M")."""
    return f"{steps / 1e6:.2f}M" if steps >= 1_000_000 else f"{steps:,}"


def _label(label: str, method) -> str:
    name = Path(str(label).rstrip("/")).name or label
    return f"{name} ({method})" if method else name


def _with_ci(mean, interval, signed: bool = False) -> str:
    mean = float_or_nan(mean)
    if math.isnan(mean):
        return "n/a"
    form = "+.1f" if signed else ".1f"
    if not interval or any(v is None or math.isnan(float_or_nan(v)) for v in interval):
        return f"{mean:{form}}"
    return f"{mean:{form}} [{float_or_nan(interval[0]):{form}}, {float_or_nan(interval[1]):{form}}]"


def _pm(mean, std) -> str:
    return f"{float_or_nan(mean):.1f} ± {float_or_nan(std):.1f}"


def _paper_cell(value: dict | None, interval) -> str:
    if not value:
        return "–"
    text = f"{value['mean']:g}" + (f" ± {value['std']:g}" if value.get("std") is not None else "")
    if interval and all(v is not None for v in interval):
        inside = float_or_nan(interval[0]) <= value["mean"] <= float_or_nan(interval[1])
        text += " (in CI)" if inside else " (outside CI)"
    return text


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")

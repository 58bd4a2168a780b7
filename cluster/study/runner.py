"""Running a study: every run trained (or resumed), then cross-play across runs, then the report.

The study directory::

    STUDY_DIR/study.json                 the study file's data, budget, seeds, --set overrides, backend; per step:
                                         status, wall time
              .lock                      held (flock) by the one ``ocv2 study run`` driving it
              runs/<name>/               one ordinary run directory per run (``ocv2 train``'s layout)
              over_training/<run>/update_<n>.json   in-run cross-play of one kept snapshot
              comparisons/<name>/        cross-run cross-play, both seat orders (summary.json, matrix.csv, heatmap.png)
              report.md  summary.json  *.png

Every step writes its result last and atomically, so a step whose result is there, parses and was made
from the step's current inputs (the fingerprints of the runs it plays, its episodes) is done: re-running
the same command after a kill skips finished runs, resumes the unfinished one from its checkpoints and
redoes only the step that was cut short (a cross-play step restarts from its beginning), or whose result
was damaged or deleted. Training
numbers do not depend on where a run was interrupted, and cross-play episode keys depend only on the
population seed, so an interrupted study reports the same numbers as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import shlex
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, ExitStack
from pathlib import Path

from cluster.api import train_population
from cluster.runtime import crossplay
from cluster.runtime.coordinator import pool_updates, same_game_and_network
from cluster.runtime.extend import extend_run, repoint_partners, take_eval_episodes
from cluster.runtime.progress import Bar
from cluster.runtime.rundir import (
    EXTENDED_KEYS,
    LOCK_NAME,
    DirLock,
    RunDir,
    RunDirError,
    extension_problem,
    write_json,
)
from cluster.study.report import write_report
from cluster.study.results import compared_settings, config_differences, evaluation_problem, read_result
from cluster.study.spec import (
    STATE_NAME,
    Comparison,
    Study,
    StudyError,
    comparison_dir,
    is_study_directory,
    parse_study,
    run_config,
    run_dir,
    with_overrides,
)
from cluster.study.state import StepRecord, StudyState
from ocv2 import boundedjson
from population import checkpoints as ckpt
from population.config import Config, ConfigError
from population.config.paper import PACKAGED_CONFIGS
from population.human import LAYOUT_MAP
from population.memory import check_fits
from population.networks import same_function
from population.numerics import DEFAULT_PRECISION
from population.policy import env_difference, env_settings, same_env
from population.xp import block_summary

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class StudyOptions:
    """How a study runs: ``ocv2 study run``'s options, given to ``plan_study`` and ``run_study`` once.

    ``budget``: the fraction of every run's env steps, applied as ``budget_mode`` says
    (``cluster.study.spec.budget_overrides``); ``seeds``: seeds per run; ``overrides``: ``--set`` config
    overrides for every run, after the study file's own. Left None (or empty), each is what the study
    directory was started with; a new directory takes 1, "truncate", each config's own seeds and none.
    ``backend``/``address``: as ``ocv2 train``; ``show_progress``: the training bars and progress lines;
    ``retrain``: runs trained with another config that are trained again; ``extend``: a larger ``budget``
    than a truncating directory keeps trains its runs on along the same schedules (``cluster.runtime.extend``).
    ``Plan.options`` holds them resolved against the directory (``budget`` and ``budget_mode`` set)."""

    budget: float | None = None
    seeds: int | None = None
    backend: str = "ray"
    address: str | None = None
    show_progress: bool = True
    budget_mode: str | None = None
    overrides: tuple[str, ...] = ()
    retrain: tuple[str, ...] = ()
    extend: bool = False


# ---------------------------------------------------------------------------------------------------
# the study directory's state
# ---------------------------------------------------------------------------------------------------


def check_folder(out: Path, what: str = "a study directory") -> None:
    """Refuse a study directory that is a file (``--out /dev/null``) or lies under one."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        kind = "a file" if out.is_file() else "a special file (a device, pipe or socket)"
        raise StudyError(f"{out}: is {kind}, not {what}")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise StudyError(f"{out}: cannot be {what}: {parent} is a file, not a directory")
            break


def read_state(out: Path) -> StudyState | None:
    """``out``'s study.json, checked field by field (``StudyState.from_json``); None when there is none."""
    check_folder(out)
    path = Path(out) / STATE_NAME
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    except UnicodeDecodeError as error:
        raise StudyError(f"{path}: unreadable ({error}); {_RESTORE}") from None
    except OSError as error:
        raise StudyError(f"{path}: cannot read: {error.strerror or error}") from None
    try:
        data = boundedjson.loads(text)
    except ValueError as error:  # not JSON, nested too deep, or an integer past Python's digit limit
        raise StudyError(f"{path}: unreadable ({error}); {_RESTORE}") from None
    return StudyState.from_json(data, path)


_RESTORE = "restore it from a backup or a pack of this study (ocv2 study pack)"


def open_state(
    study: Study,
    out: Path,
    budget: float | None,
    seeds: int | None,
    backend: str,
    overrides: Sequence[str] = (),
    mode: str | None = None,
    extend: bool = False,
    retrain: Sequence[str] = (),
) -> StudyState:
    """The study directory's state, created or checked: a directory keeps the budget, its mode, the seed
    count and ``--set`` overrides it was started with (options left out on a later run take those values);
    with ``extend``, a larger budget of a truncating directory is taken and recorded (``extensions``). The study
    may add runs and comparisons to the ones the directory records, not drop them or give a run another config
    file (``check_same_study``; a run in ``retrain`` may take another)."""
    state = read_state(out)
    given_overrides = tuple(overrides) or None
    if extend and budget is None:
        raise StudyError("--extend needs --budget F, the larger budget to train the study's runs on to")
    if state is not None:
        if state.study != study.name:
            raise StudyError(f"{out}: holds study {state.study!r}, not {study.name!r}; choose another --out")
        check_same_study(study, out, state, retrain)
        if extend and budget != state.budget:
            _extend_budget(state, out, budget)
        kept_options = (
            ("--budget", budget, state.budget),
            ("--budget-mode", mode, state.budget_mode),
            ("--seeds", seeds, state.seeds),
            ("--set", given_overrides, state.overrides),
        )
        for flag, given, kept in kept_options:
            if given is not None and given != kept:
                shown = f"{flag} {kept}" if kept is not None else f"no {flag} (each config's own)"
                if flag == "--set":
                    shown = " ".join(f"--set {o}" for o in kept) or "no --set"
                longer = flag == "--budget" and state.budget_mode == "truncate" and given > kept
                raise StudyError(
                    f"{out}: was started with {shown}; pass the same value (or none) to continue "
                    "it, or choose another --out"
                    + ("; or add --extend to train its runs on along the same schedules" if longer else "")
                )
    else:
        if extend:
            raise StudyError(f"--extend: {out} holds no study yet; a new study takes --budget without it")
        if out.exists() and not out.is_dir():
            raise StudyError(f"{out}: is a file, not a study directory")
        if out.is_dir() and any(p.name not in ("runs", ".lock") for p in out.iterdir()):
            raise StudyError(f"{out}: exists and is not a study directory (no {STATE_NAME}); choose another --out")
        state = StudyState(
            study=study.name,
            spec=study.raw,
            budget=1.0 if budget is None else budget,
            budget_mode="truncate" if mode is None else mode,
            seeds=seeds,
            overrides=given_overrides or (),
            created=time.time(),
            backend=backend,
        )
    # The backend stays the one that last ran a step (run_study sets it): a rerun that runs nothing keeps it.
    state.source, state.spec = str(study.path), study.raw
    return state


def check_same_study(study: Study, out: Path, state: StudyState, retrain: Sequence[str] = ()) -> None:
    """Refuse ``study`` for directory ``out`` (whose study.json is ``state``) when it is another study file of the
    same name: one that lacks a run or a played comparison the directory records (its results would drop out of the
    report, their pictures left stale) or gives a recorded run another config file (a run in ``retrain`` may take
    one). Config files are compared by where they lie, or else their bytes, when the file the directory was run from
    is still there, else by name (a directory unpacked from another machine)."""
    kept_runs = _named(state.spec.get("runs"))
    # A comparison not yet played may go (e.g. one its runs cannot play, which check_comparisons refuses): only a
    # played one has results the report would drop.
    played = [
        name
        for name in _named(state.spec.get("comparisons"))
        if getattr(state.steps.get(f"compare {name}"), "status", None) == "done"
    ]
    lost = [f"run {name!r}" for name in kept_runs if name not in {r.name for r in study.runs}]
    lost += [f"comparison {name!r}" for name in played if name not in {c.name for c in study.comparisons}]
    recorded = f"{out} holds study {state.study!r} run from {state.source or 'a study file'}"
    advice = (
        "run it with that study file (a study file may add runs and comparisons, not drop them), "
        "or choose another --out"
    )
    if lost:
        raise StudyError(f"{study.origin}: has no {', '.join(lost)}, which {recorded} records; {advice}")
    source = Path(state.source) if state.source else None
    for run in study.runs:
        config = kept_runs.get(run.name)
        if not isinstance(config, str) or run.name in retrain:
            continue
        if source is not None and source.is_file():
            try:
                kept_path, given = (source.parent / config).resolve(), Path(run.config).resolve()
            except RuntimeError as error:  # a symbolic link loop (Python 3.11-3.12)
                raise StudyError(f"run {run.name!r}: its config file cannot be found: {error}") from None
            same = kept_path == given or _same_bytes(kept_path, given)  # e.g. the same file in another checkout
            kept = str(kept_path)
        else:
            same, kept = Path(config).name == Path(run.config).name, config
        if not same:
            raise StudyError(
                f"{study.origin}: run {run.name!r} takes config {run.config}, but {recorded} gives it {kept}; "
                f"{advice}, or pass --retrain {run.name} to train it again from the new config"
            )


def _same_bytes(first: Path, second: Path) -> bool:
    try:
        return first.read_bytes() == second.read_bytes()
    except OSError:
        return False


def _named(entries) -> dict:
    """A kept spec's ``runs`` or ``comparisons``: name -> its config (None for a comparison), in order."""
    if not isinstance(entries, list):
        return {}
    return {e["name"]: e.get("config") for e in entries if isinstance(e, dict) and isinstance(e.get("name"), str)}


def _extend_budget(state: StudyState, out: Path, budget: float) -> None:
    """Raise ``state``'s budget to ``budget`` for ``--extend`` (the runs follow in ``run_study``)."""
    if state.budget_mode != "truncate":
        raise StudyError(
            f"--extend: {out} compresses each schedule into its budget (--budget-mode compress), so a larger "
            "budget is another schedule, not more of the same; choose another --out"
        )
    if budget < state.budget:
        raise StudyError(f"--extend: --budget {budget:g} is less than the {state.budget:g} {out} has trained to")
    state.extensions.append({"from": state.budget, "to": budget, "at": time.time()})
    state.budget = budget


def study_source(state: StudyState, out: Path) -> Path:
    """The study file a directory was run from, or the shipped study of that name when it is gone (run from
    another checkout, unpacked elsewhere); the recorded path (or ``out/study.yaml``) when neither is there."""
    source = Path(state.source or Path(out) / "study.yaml")
    if not source.is_file():
        shipped = Path(str(PACKAGED_CONFIGS / "studies")) / source.name
        source = shipped if shipped.is_file() else source
    return source


def continue_hint(path) -> str | None:
    """What ``ocv2 study run`` says when given a study directory or its study.json for a study file: the command
    that continues it, from the study file and options its study.json records; None for anything else."""
    path = Path(path).resolve()
    if not is_study_directory(path):
        return None
    out = path if path.is_dir() else path.parent
    what = f"the {STATE_NAME} of study directory {out}" if path.is_file() else "a study directory"
    try:
        state = read_state(out)
    except StudyError as error:
        return f"{path}: is {what}, not a study file (and {error})"
    source = study_source(state, out)
    words = ["ocv2", "study", "run", str(source), "--out", str(out)]
    words += ["--budget", str(state.budget), "--budget-mode", state.budget_mode]  # str: exactly the kept number
    words += ["--seeds", str(state.seeds)] if state.seeds is not None else []
    words += [word for override in state.overrides for word in ("--set", override)]
    words += ["--backend", state.backend] if state.backend in ("ray", "local") else []
    gone = "" if source.is_file() else f" (the study file it was run from, {source}, is gone: give it)"
    return f"{path}: is {what} (study {state.study!r}), not a study file; continue it with: {shlex.join(words)}{gone}"


def kept_study(state: StudyState, out: Path) -> Study:
    """The study a study directory runs: the file's data it keeps, with the ``--set`` overrides it was started with."""
    source = study_source(state, out)
    try:
        study = parse_study(state.spec, source)
    except StudyError as error:
        gone = ""
        if not source.is_file():
            gone = (
                f" (its configs are named relative to the study file it was run from, {source}, which is gone: "
                f"run `ocv2 study run STUDY.yaml --out {out}` once with that file where it lies now)"
            )
        raise StudyError(f"{Path(out) / STATE_NAME}: spec: {error}{gone}") from None
    kept = dataclasses.replace(study, where=f"{Path(out) / STATE_NAME} (the spec it keeps from {study.path.name})")
    return with_overrides(kept, list(state.overrides))


class StateFile:
    """``study.json``, rewritten atomically whenever a step starts, advances or ends."""

    def __init__(self, out: Path, state: StudyState):
        self.path, self.state = Path(out) / STATE_NAME, state

    def save(self) -> None:
        """Write the state to study.json (atomically)."""
        write_json(self.path, self.state.to_json())

    def step(self, name: str) -> StepRecord:
        """Step ``name``'s record, created "left" with no wall time when it has none."""
        return self.state.step(name)

    def mark(self, name: str, **changes) -> None:
        """Update step ``name``'s record with ``changes`` and save."""
        self.step(name).update(**changes)
        self.save()

    def timer(self, name: str) -> StepTimer:
        """A ``StepTimer`` of step ``name``, counting from now."""
        return StepTimer(self, name)


class StepTimer:
    """Adds wall time to a step as it goes (a kill loses at most the time since the last tick)."""

    def __init__(self, state: StateFile, name: str):
        self.state, self.name, self.last = state, name, time.time()

    def tick(self, **changes) -> None:
        """Add the wall time since the last tick to the step, record ``changes`` and save."""
        now = time.time()
        step = self.state.step(self.name)
        step.wall_s = round(step.wall_s + now - self.last, 1)
        self.last = step.ticked = now  # lets ``study_status`` add the time since, while the step runs
        self.state.mark(self.name, **changes)


# ---------------------------------------------------------------------------------------------------
# running
# ---------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Plan:
    """What ``run_study`` will do, checked before anything is written: the study with the directory's
    ``--set`` overrides, its state (created or read, not saved yet), the options, every run's config and the runs
    trained to an earlier budget of the study that ``run_study`` extends first."""

    study: Study
    out: Path
    state: StudyState
    options: StudyOptions
    configs: dict
    retrain: tuple[str, ...] = ()
    extend: tuple[str, ...] = ()
    reevaluate: tuple[str, ...] = ()  # runs whose eval.episodes the study changed: evaluated again, not retrained


def plan_study(study: Study, out, options: StudyOptions = StudyOptions()) -> Plan:
    """Every check ``run_study`` makes before it writes: the directory (not a file, the same options it was
    started with), every run's config at the budget and seed count, that each fits this machine's memory,
    and that every run already trained in it was trained with the config the study now asks for (a run
    in ``options.retrain`` may differ: ``run_study`` trains it again, once: ``Plan.retrain`` holds only those
    that still differ). Writes nothing.

    Returns the ``Plan``; raises ``StudyError`` naming what is refused (``RunDirError`` for a run
    directory that cannot be read)."""
    out = Path(out).resolve()
    backend, address = options.backend, options.address
    state = open_state(
        study,
        out,
        options.budget,
        options.seeds,
        backend,
        options.overrides,
        options.budget_mode,
        options.extend,
        options.retrain,
    )
    study = with_overrides(study, list(state.overrides))
    retrain = tuple(dict.fromkeys(options.retrain))
    options = dataclasses.replace(
        options,
        budget=state.budget,
        seeds=state.seeds,
        budget_mode=state.budget_mode,
        overrides=state.overrides,
        retrain=retrain,
    )
    # Every config at this budget and seed count first: one they refuse fails before the directory is written.
    configs = {
        run.name: run_config(study, run, out, options.budget, options.seeds, options.budget_mode) for run in study.runs
    }
    place = "local" if backend == "local" else "ray" if address is None else "cluster"
    for name, config in configs.items():
        try:
            check_fits(config, place)
        except ConfigError as error:
            raise StudyError(f"{study.origin}: run {name!r}: {error}") from None
    check_comparisons(study, configs)
    _check_retrain(study, out, retrain)
    differs = {run.name: trained_differences(run_dir(out, run.name), configs[run.name]) for run in study.runs}
    retrain = _still_to_retrain(study, differs, retrain)
    extend, reevaluate = [], []
    for run in study.runs:
        differences = differs[run.name]
        if run.name in retrain:
            continue
        # Episodes per pair change the evaluation only (eval is outside the fingerprint): evaluated again.
        if any(d.split(":")[0] in REEVALUATED_KEYS for d in differences):
            reevaluate.append(run.name)
            differences = [d for d in differences if d.split(":")[0] not in REEVALUATED_KEYS]
        if not differences:
            continue
        problem = extension_problem(RunDir(run_dir(out, run.name)).load_config(), configs[run.name])
        longer = all(d.split(":")[0] in EXTENDED_KEYS for d in differences) and problem is None
        if longer and state.extensions:  # trained to an earlier budget of this study: run_study extends it
            extend.append(run.name)
            continue
        more = f" and {len(differences) - 2} more" if len(differences) > 2 else ""
        why = f"; it cannot be extended: {problem}" if state.extensions and problem else ""
        raise StudyError(
            f"{study.origin}: run {run.name!r}: {run_dir(out, run.name)} was trained with another config "
            f"({'; '.join(differences[:2])}{more}){why}; undo the change, or pass --retrain {run.name} to train it "
            "again (the trained run and its cross-play move to replaced/)"
        )
    check_partners_from(study, configs, out, changing=(*retrain, *extend))
    return Plan(study, out, state, options, configs, retrain, tuple(extend), tuple(reevaluate))


#: Compared run settings that a study may change in a trained run without training it again: its evaluation
#: is made again (``take_eval_episodes``).
REEVALUATED_KEYS = ("eval.episodes",)


def steps_to_run(plan: Plan) -> list[str]:
    """The steps ``run_study`` would run for ``plan``: those not done or whose result no longer counts
    (``result_problem``), every step when a run is retrained, extended or evaluated again. Empty: a rerun
    only writes the report again (``ocv2 study run`` then starts no Ray)."""
    steps = study_steps(plan.study)
    kept = read_state(plan.out)
    if plan.retrain or plan.extend or plan.reevaluate or (kept is not None and kept.budget != plan.state.budget):
        return [step.name for step in steps]
    return [
        step.name for step in steps if _why_run(step, plan.state.steps.get(step.name, StepRecord()), plan) is not None
    ]


def _why_run(step: Step, record: StepRecord, plan: Plan) -> str | None:
    """Why ``run_study`` runs ``step`` (recorded as ``record``): "not done", or the ``result_problem`` of a done
    step whose result no longer counts. None: done and kept. ``steps_to_run`` asks the same question before Ray."""
    if not record.done:
        return "not done"
    return result_problem(step, plan.study, plan.out, plan.configs)


#: The layouts the 2019 human data covers, and with it a BC human proxy (``population.human``).
HUMAN_LAYOUTS = tuple(LAYOUT_MAP.values())


def check_partners_from(study: Study, configs: dict, out: Path, changing: Sequence[str] = ()) -> None:
    """Refuse, before anything trains, an FCP run whose ``partners_from`` run cannot give its pool: a run of another
    game or network, or ``population.fcp.checkpoints`` naming an update the partner run keeps no snapshot of. The FCP
    run's own start refused these too, but only once the partner run had trained its whole budget. The snapshots
    of a partner run in ``changing`` (retrained or extended now) are not those on disk: its own start checks them."""
    for run in study.runs:
        if run.partners_from is None:
            continue
        where = f"{study.origin}: run {run.name!r}.partners_from"
        learner, partner = configs[run.name], configs[run.partners_from]
        if not same_game_and_network(partner, learner):
            difference = env_difference(partner.env_kwargs, learner.env_kwargs) or (
                "its model section differs"
                if same_function(partner.model) != same_function(learner.model)
                else f"its ppo.activation is {partner.ppo.activation!r}, not {learner.ppo.activation!r}"
            )
            raise StudyError(
                f"{where}: run {run.partners_from!r} trains another game or network than run {run.name!r} "
                f"({difference}); FCP partners play the learner's game with its network"
            )
        if run.partners_from in changing:
            continue
        try:  # the snapshots the partner run will keep (an extended one's earlier stops' too)
            pool_updates(learner, partner, run_dir(out, run.partners_from))
        except (RunDirError, ckpt.CheckpointError) as error:  # a damaged manifest.json of the partner run, too
            raise StudyError(f"{where}: {error}") from None


def check_comparisons(study: Study, configs: dict) -> None:
    """Refuse, before anything trains, a comparison that cannot be played: runs of different games (layout or
    env settings), runs trained at different ``run.precision``, or ``human_proxy: true`` on a layout with no human
    data. ``configs``: every run's config (``run_config``). The ``StudyError`` names the study file and the
    comparison."""
    for comparison in study.comparisons:
        where = f"{study.origin}: comparison {comparison.name!r}"
        first = comparison.runs[0]
        env = configs[first].env_kwargs
        for name in comparison.runs[1:]:
            other = configs[name].env_kwargs
            if not same_env(other, env):
                raise StudyError(
                    f"{where}: run {name!r} plays another game than run {first!r} ({env_difference(other, env)}); "
                    "cross-play needs one game: compare runs of the same layout and env settings"
                )
        precisions = {name: configs[name].run.precision for name in comparison.runs}
        if len(set(precisions.values())) > 1:
            shown = ", ".join(f"{name}: {precision}" for name, precision in precisions.items())
            raise StudyError(
                f"{where}: its runs train at different run.precision ({shown}); give the compared runs one "
                "run.precision (set:)"
            )
        layout = env_settings(env).get("layout")
        if comparison.human_proxy and layout not in HUMAN_LAYOUTS:
            raise StudyError(
                f"{where}: human_proxy: true, but layout {layout!r} has no human data (a BC human proxy exists "
                f"only for {', '.join(HUMAN_LAYOUTS)}); set human_proxy: false or compare runs of one of those"
            )


def _still_to_retrain(study: Study, differs: dict, asked: tuple[str, ...]) -> tuple[str, ...]:
    """The runs of ``asked`` (``--retrain``) to set aside now: those trained with another config than planned
    (``differs``: run name -> ``trained_differences``), and FCP runs whose partner run is set aside. A run
    already created with the planned config (by an earlier ``--retrain``, then stopped) is continued, so the
    same command resumes instead of starting that run over each time."""
    chosen: list[str] = []
    for run in study.runs:  # a partner run comes before the runs that take it (spec.py checks)
        if run.name in asked and (differs[run.name] or run.partners_from in chosen):
            chosen.append(run.name)
    return tuple(chosen)


def _check_retrain(study: Study, out: Path, retrain: tuple[str, ...]) -> None:
    names = [r.name for r in study.runs]
    for name in retrain:
        if name not in names:
            raise StudyError(f"--retrain {name}: the study has no run named {name!r} (its runs: {', '.join(names)})")
        for run in study.runs:  # an FCP run whose partner run is retrained would keep the old partners
            if (
                run.partners_from == name
                and run.name not in retrain
                and (run_dir(out, run.name) / "config.yaml").is_file()
            ):
                raise StudyError(
                    f"--retrain {name}: run {run.name!r} took its partners from it; pass --retrain {run.name} too"
                )


def trained_differences(path: Path, planned: Config) -> list[str]:
    """How the config the run in ``path`` was created with differs from ``planned`` ("ppo.lr: 0.0004 in the
    run, 0.01 now"); empty when nothing was trained there yet or nothing that matters differs."""
    if not (Path(path) / "config.yaml").is_file():
        return []
    try:
        trained = RunDir(path).load_config()
    except RunDirError as error:
        raise StudyError(str(error)) from None
    return config_differences(trained, planned)


def run_study(
    study: Study,
    out,
    options: StudyOptions = StudyOptions(),
    say: Callable[[str], None] = log.info,
    session: Callable[[bool], AbstractContextManager] | None = None,
) -> dict:
    """Train every unfinished run, run the cross-play steps, write the report; ``say`` gets one line per
    step. ``options``: as ``plan_study``, whose checks come first. ``session(needed)``: a context the steps run in,
    entered under the directory's lock with whether any step will run (``steps_to_run``); the CLI starts Ray there
    only when one will, so a rerun with nothing to do starts none, decided on what the lock lets no other driver
    change.

    Returns the state (``steps``: name -> status "done" or "blocked" with a reason, ``report``: the
    paths written). Raises ``StudyError`` for what ``plan_study`` refuses and for a directory another
    process is running; errors of training and cross-play (``RunDirError``, ``CheckpointError``,
    ``RayBackendError``, ...) pass through."""
    arguments = (study, out, options)
    out = plan_study(*arguments).out  # refused here, nothing is written
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    lock = DirLock(out)
    try:
        lock.acquire(advice="wait for it to finish or stop it before running the study again")
    except RunDirError as error:
        raise StudyError(str(error)) from None
    with ExitStack() as held:  # the session closes first, then the lock is released, then an unused new folder goes
        if created:
            held.callback(_remove_if_unused, out)
        held.callback(lock.release)
        plan = plan_study(*arguments)  # again under the lock: what another driver did before it is seen
        if session is not None:
            held.enter_context(session(bool(steps_to_run(plan))))
        study, configs = plan.study, plan.configs
        kept = read_state(out)  # before _set_aside saves the plan's state
        state = StateFile(out, plan.state)
        for name in plan.retrain:
            _set_aside(study, out, name, state, say)
        for name in (n for n in plan.options.retrain if n not in plan.retrain):
            say(
                f"study {study.name}: --retrain {name}: nothing to set aside, {run_dir(out, name)} holds no run of "
                "another config (an earlier --retrain made it); it is continued, not started over"
            )
        if kept is not None and kept.budget != plan.state.budget:  # --extend, now: the old results step aside
            _set_aside_results(study, out, kept.budget, state, say)
        state.save()
        for name in plan.extend:  # first: the extension keeps the old stop's evaluation under extended/
            path = run_dir(out, name)
            if (record := extend_run(path, configs[name])) is not None:
                say(
                    f"study {study.name}: run {name}: extended from update {record['from_updates']} to "
                    f"{record['to_updates']} (its evaluation there kept in {path / 'extended'})"
                )
        for name in plan.reevaluate:
            old = take_eval_episodes(run_dir(out, name), configs[name])
            if old is not None:
                say(
                    f"study {study.name}: run {name}: evaluated again with eval.episodes "
                    f"{configs[name].eval.episodes} (was {old}; what was evaluated with it is kept in "
                    f"{run_dir(out, name) / 'reevaluated'})"
                )
                _set_aside(study, out, name, state, say, out / "reevaluated" / time.strftime("%Y%m%d-%H%M%S"), False)
        steps = study_steps(study)
        for number, step in enumerate(steps, start=1):
            name = step.name
            record = state.step(name)
            if (why := _why_run(step, record, plan)) is None:
                continue
            if record.done:
                say(f"study {study.name}: {name}: {why}; doing the step again")
            say(f"study {study.name}: [{number}/{len(steps)}] {name}")
            timer = state.timer(name)
            state.step(name).reason = None  # a step blocked before may run now
            # The backend that ran the step: the report names each one when a study's steps ran on several.
            state.state.backend = plan.options.backend
            state.mark(name, status="running", started=timer.last, ticked=timer.last, backend=plan.options.backend)
            try:
                result = _RUN_STEP[step.kind](plan, step.target, timer)
            except (StudyBlocked, StudyError) as blocked:  # recorded, not left "running"; the other steps go on
                timer.tick(status="blocked", reason=str(blocked))
                say(f"study {study.name}: {name} blocked: {blocked}")
                continue
            timer.tick(status="done", finished=time.time(), **(result or {}))
        state.state.report = write_report(study, out, state.state, configs)
        state.save()
        return state.state


def _remove_if_unused(out: Path) -> None:
    """Remove the study directory this call made when it holds nothing but its lock file: the session could not
    start (Ray unreachable), and a failed command leaves no empty study behind (as ``RunDir.open`` does for a run)."""
    if {p.name for p in out.iterdir()} <= {LOCK_NAME}:
        (out / LOCK_NAME).unlink(missing_ok=True)
        out.rmdir()


def _set_aside(
    study: Study,
    out: Path,
    name: str,
    state: StateFile,
    say: Callable[[str], None],
    target: Path | None = None,
    with_run: bool = True,
) -> None:
    """Move run ``name`` (unless not ``with_run``), its over-training cross-play and the comparisons that play it to
    ``target`` (default ``out/replaced/<time>/``; nothing is deleted) and mark their steps left: ``--retrain``, and
    the study-level results of a run evaluated again with other episodes per pair (``reevaluated/<time>/``)."""
    target = out / "replaced" / time.strftime("%Y%m%d-%H%M%S") if target is None else target
    moves = [(run_dir(out, name), Step("train", name))] if with_run else []
    moves.append((out / "over_training" / name, Step("over_training", name)))
    moves += [(comparison_dir(out, c.name), Step("compare", c.name)) for c in study.comparisons if name in c.runs]
    for source, step in moves:
        state.state.steps.pop(step.name, None)
        if source.exists():
            destination = target / source.relative_to(out)
            destination.parent.mkdir(parents=True, exist_ok=True)
            source.rename(destination)
            say(f"study {study.name}: {'--retrain ' if with_run else ''}{name}: moved {source} to {destination}")
    state.save()


def _set_aside_results(study: Study, out: Path, budget: float, state: StateFile, say: Callable[[str], None]) -> None:
    """Move the report and the cross-play results made at ``budget`` to ``out/extended/budget_<budget>/`` (a
    study extended with ``--extend``; nothing is deleted) and mark the cross-play steps left."""
    target = out / "extended" / f"budget_{budget:g}"
    if target.exists():  # an extension to this budget set aside before (then the study went on at it)
        target = target.with_name(f"{target.name}_{time.strftime('%Y%m%d-%H%M%S')}")
    names = ["report.md", "summary.json", *(p.name for p in out.glob("*.png")), "over_training", "comparisons"]
    for name in names:
        source = out / name
        if source.exists():
            target.mkdir(parents=True, exist_ok=True)
            source.rename(target / name)
    for step in study_steps(study):
        if step.kind != "train":
            state.state.steps.pop(step.name, None)
        elif step.name in state.state.steps:  # trains on: not done (its wall time so far stays)
            state.state.steps[step.name].status = "left"
    say(f"study {study.name}: --extend: the results at budget {budget:g} moved to {target}")


class StudyBlocked(Exception):
    """A step that cannot run yet for a reason the user must fix (e.g. a missing human proxy)."""


#: The kinds of study steps, in the order a run's steps come: train it, cross-play its snapshots; then
#: the comparisons.
STEP_KINDS = ("train", "over_training", "compare")


@dataclasses.dataclass(frozen=True)
class Step:
    """One step of a study: its ``kind`` (one of ``STEP_KINDS``) and ``target``, the name of the run it
    trains or cross-plays or of the comparison it plays."""

    kind: str
    target: str

    @property
    def name(self) -> str:
        """The step's key in study.json and its name in messages and ``ocv2 study status``: "train sp"."""
        return f"{self.kind} {self.target}"


def study_steps(study: Study) -> list[Step]:
    """The steps of ``study`` in the order ``run_study`` takes them: per run its training, then the
    cross-play of its snapshots (when the study asks for it) as soon as it has finished; then every
    comparison."""
    steps = []
    for run in study.runs:
        steps.append(Step("train", run.name))
        if run.name in study.over_training:
            steps.append(Step("over_training", run.name))
    steps += [Step("compare", c.name) for c in study.comparisons]
    return steps


def result_problem(step: Step, study: Study, out: Path, configs: dict) -> str | None:
    """Why ``step``, marked done, must run again: its result is missing, does not parse, or was made
    from other inputs than the step has now; None when it is done."""
    kind, name = step.kind, step.target
    if kind == "train":
        return run_problem(run_dir(out, name))
    if kind == "compare":
        comparison = next((c for c in study.comparisons if c.name == name), None)
        path = comparison_dir(out, name) / "summary.json"
        data, problem = read_result(path)
        if problem is None and "orders" not in data and "pairs" not in data:  # "pairs": a study made before "orders"
            problem = f"{path} is not a result of this step (no orders)"
        if problem is None and comparison is not None:
            kept = data.get("study_inputs")
            if kept is not None and kept != comparison_inputs(comparison, configs):
                problem = f"{path} was made from other runs or episodes than the comparison has now"
            elif comparison.human_proxy:
                problem = _proxy_problem(path, data, configs[comparison.runs[0]])
        return problem
    if kind != "over_training":  # a new kind must say when its result counts as done, not pass as this one
        raise ValueError(f"result_problem: unknown study step kind {kind!r} (STEP_KINDS: {', '.join(STEP_KINDS)})")
    folder = out / "over_training" / name
    data, problem = read_result(folder / "done.json", ("snapshots",))
    if problem is not None:
        return problem
    if data.get("study_inputs") is not None:
        try:
            trained = RunDir(run_dir(out, name)).load_config()
        except RunDirError as error:
            return str(error)
        if data["study_inputs"] != over_training_inputs(trained):
            return f"{folder / 'done.json'} was made from another training of run {name!r}"
    snapshots = data["snapshots"] if isinstance(data["snapshots"], list) else [None]
    for update in snapshots:  # each snapshot's result, which the report reads
        if not isinstance(update, int) or isinstance(update, bool):
            return f"{folder / 'done.json'} lists a snapshot that is not an update number: {update!r}"
        problem = read_result(folder / f"update_{update:07d}.json", ("sp_mean", "matrix"))[1]
        if problem is not None:
            return problem
    return None


def _proxy_problem(path: Path, data: dict, config: Config) -> str | None:
    """Why a comparison's result against the human proxy is stale: the proxy file now holds another policy (it
    was trained again). A result made before the proxy's id was recorded, or whose proxy is gone, stands."""
    made = data.get("human_proxy_id")
    if made is None:
        return None
    try:
        now = crossplay.resolve_source(crossplay.HUMAN_PROXY + config.env_kwargs["layout"]).ids[0]
    except crossplay.CrossPlayError:
        return None
    if now == made:
        return None
    return f"{path} was played against another human proxy than the one there now (it was trained again)"


def comparison_inputs(comparison: Comparison, configs: dict) -> dict:
    """What a comparison's result depends on: how its runs were trained (``inputs_fingerprint``), the
    episodes and key stream, the human proxy."""
    first = configs[comparison.runs[0]]
    return {
        "runs": {r: inputs_fingerprint(configs[r]) for r in comparison.runs},
        "episodes": first.eval.episodes,
        "seed": first.population.seed,
        "human_proxy": comparison.human_proxy,
    }


def over_training_inputs(config: Config) -> dict:
    """What an over-training result depends on: how the run was trained (``inputs_fingerprint``) and
    the episodes per pair."""
    return {"run": inputs_fingerprint(config), "episodes": config.eval.episodes}


def inputs_fingerprint(config: Config) -> str:
    """A hash of what ``trained_differences`` compares: the training settings and eval.episodes, but not
    where an FCP run's partners lie (a study directory carried to another machine keeps its results)."""
    text = json.dumps(compared_settings(config), sort_keys=True, default=list)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def run_problem(path: Path) -> str | None:
    """Why the run in ``path`` is not trained and evaluated (None: it is, and is never trained again). A run
    whose training is done but whose cross-play is missing, damaged or not the one its config asks for
    (``evaluation_problem``) is evaluated again by ``_train``: its resume trains nothing."""
    if not (path / "config.yaml").is_file():
        return f"{path} holds no run"
    run = RunDir(path)
    try:
        status = run.read_manifest().get("status")
    except RunDirError as error:
        return str(error)
    if status != "finished":
        return f"{path} has not finished training"
    summary_path = path / "xp" / "summary.json"
    summary, problem = read_result(summary_path, ("sp_mean", "xp_mean", "num_policies"))
    if problem is not None:
        return problem
    try:
        return evaluation_problem(summary_path, summary, run.load_config())
    except RunDirError as error:
        return str(error)


def run_finished(path: Path) -> bool:
    """Trained and evaluated: never trained again."""
    return run_problem(path) is None


def _train(plan: Plan, name: str, timer: StepTimer) -> dict:
    """Train (or resume) run ``name`` with its evaluation, unless it has finished; returns what
    study.json records of the step."""
    out, options = plan.out, plan.options
    path, config = run_dir(out, name), plan.configs[name]
    if run_finished(path):
        return {}
    if options.address:
        config = dataclasses.replace(config, cluster=dataclasses.replace(config.cluster, address=options.address))
    resume = (path / "config.yaml").is_file()
    if resume and repoint_partners(path, config):
        log.info(f"study {plan.study.name}: run {name}: its partners now lie in {config.population.fcp.partners}")
    train_population(
        config,
        path,
        backend=options.backend,
        resume=resume,
        show_progress=options.show_progress,
        evaluate=True,
        on_chunk=lambda event: timer.tick(update=event.update),
    )
    return {"update": config.ppo.num_updates}


def _over_training(plan: Plan, name: str, timer: StepTimer) -> dict:
    """In-run cross-play of every kept snapshot of run ``name`` whose result is not there yet (or was
    made from another training); raises ``StudyBlocked`` while the run has not finished."""
    out, options = plan.out, plan.options
    path = run_dir(out, name)
    if not run_finished(path):
        raise StudyBlocked(f"run {name} has not finished")
    created = RunDir.existing(path).load_config()  # its snapshots are protected for good
    try:
        snapshots = ckpt.run_snapshots(path, created.ppo.num_updates, created.run.num_checkpoints)
    except ckpt.CheckpointError as error:  # a damaged manifest.json
        raise RunDirError(str(error)) from None
    folder = out / "over_training" / name
    inputs = over_training_inputs(created)
    todo = []
    for update in snapshots:  # a snapshot's result counts when it parses and was made from this training
        data, problem = read_result(folder / f"update_{update:07d}.json", ("sp_mean", "matrix"))
        if problem is None and data.get("study_inputs") not in (None, inputs):
            problem = "made from another training"
        if problem is not None:
            todo.append(update)
    if todo:
        groups = {u: _source(str(path), str(u)) for u in todo}
        jobs = created.population.num_seeds * len(todo)
        with crossplay.players(options.backend, jobs, options.address, precision=created.run.precision) as workers:
            for update in todo:
                group = groups[update]
                result = crossplay.play_matrix(
                    [group], [group], workers, crossplay.xp_key(created.population.seed), created.eval.episodes
                )
                ids = list(group.ids)
                summary = block_summary(result.matrix, ids, ids)
                if options.show_progress:  # minutes per snapshot: say where it is and what it found
                    log.info(
                        f"  over_training {name}: snapshot {snapshots.index(update) + 1}/{len(snapshots)} (update {update}): "
                        f"SP {summary['sp_mean']:.1f}, XP {summary['xp_mean']:.1f}, gap {summary['gap']:.1f}"
                    )
                summary.update(
                    update=update,
                    env_steps_per_seed=update * created.ppo.steps_per_update,
                    episodes_per_pair=created.eval.episodes,
                    precision=created.run.precision,
                    matrix=result.matrix.round(4).tolist(),
                    study_inputs=inputs,
                )
                write_json(folder / f"update_{update:07d}.json", summary)
                timer.tick()
    done = snapshots
    write_json(folder / "done.json", {"snapshots": done, "study_inputs": inputs})
    return {"snapshots": len(done)}


def _compare(plan: Plan, name: str, timer: StepTimer) -> dict:
    """Comparison ``name``: its runs (and the human proxy, when it asks for one) against each other in
    both seats; raises ``StudyBlocked`` while a run has not finished or the human proxy is missing."""
    out, options, configs = plan.out, plan.options, plan.configs
    comparison = next(c for c in plan.study.comparisons if c.name == name)
    missing = [r for r in comparison.runs if not run_finished(run_dir(out, r))]
    if missing:
        raise StudyBlocked(f"runs {', '.join(missing)} have not finished")
    first = configs[comparison.runs[0]]
    # Labelled by run name: the report and summary do not depend on where the study directory lies.
    groups = [dataclasses.replace(_source(str(run_dir(out, r))), label=r) for r in comparison.runs]
    if comparison.human_proxy:
        groups.append(_source(crossplay.HUMAN_PROXY + first.env_kwargs["layout"]))
    try:
        crossplay.check_same_env(groups)
    except crossplay.CrossPlayError as error:  # runs of two games are refused by plan_study; a proxy may differ
        raise StudyError(f"comparison {comparison.name!r}: {error}") from None
    try:
        precision = crossplay.played_precision(groups)
    except crossplay.CrossPlayError as error:
        raise StudyError(
            f"comparison {comparison.name!r}: {error}; give the compared runs one run.precision (set:)"
        ) from None
    result = compare(groups, options, first.population.seed, first.eval.episodes, comparison.name, timer, precision)
    result.summary["study_inputs"] = comparison_inputs(comparison, configs)
    result.summary["precision"] = precision
    if comparison.human_proxy:  # which proxy: retraining it (ocv2 human proxy) makes the result stale
        result.summary["human_proxy_id"] = groups[-1].ids[0]
    folder = comparison_dir(out, comparison.name)
    crossplay.write_seat_fair_outputs(result.matrix, folder, result.summary, crossplay.policy_env(groups[0].env))
    return {}


#: What runs each kind of step: a function of the plan, the step's target and its timer that returns
#: what study.json records of the step.
_RUN_STEP: dict[str, Callable[[Plan, str, StepTimer], dict]] = {
    "train": _train,
    "over_training": _over_training,
    "compare": _compare,
}


def _source(text: str, checkpoint: str = "final") -> crossplay.PolicyGroup:
    try:
        return crossplay.resolve_source(text, checkpoint)
    except crossplay.CrossPlayError as error:
        if not text.startswith(crossplay.HUMAN_PROXY):
            raise StudyError(str(error)) from None
        raise StudyBlocked(str(error)) from None  # a missing proxy's message says how to make it


def _play(options: StudyOptions, rows, cols, seed: int, episodes: int, label: str, precision: str) -> crossplay.Matrix:
    jobs = sum(len(g.names) for g in rows) * len(cols)
    players = crossplay.players(options.backend, jobs, options.address, precision=precision)
    with players as workers, Bar(label, options.show_progress) as bar:
        return crossplay.play_matrix(rows, cols, workers, crossplay.xp_key(seed), episodes, progress=bar)


# ---------------------------------------------------------------------------------------------------
# cross-run cross-play, both seat orders
# ---------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ComparisonResult:
    """What ``compare`` returns: the played matrix and its seat-fair summary."""

    matrix: crossplay.SeatFairMatrix  # every group against every group; the one matrix holds both seat orders
    summary: dict  # crossplay.summarize_seat_fair's


def compare(
    groups,
    options: StudyOptions,
    seed: int,
    episodes: int,
    label: str,
    timer: StepTimer | None = None,
    precision: str = DEFAULT_PRECISION,
) -> ComparisonResult:
    """Every group against every group in both seats, traced at ``precision`` (a ``run.precision``); a group
    against itself is its own in-run cross-play (same episode keys); ``label`` names the progress lines.

    Returns the matrix (rows in seat 0, so cell (i, j) and (j, i) are the two orders of a pair) and
    ``crossplay.summarize_seat_fair``'s summary of it: ``blocks`` (the mean of both orders) and ``orders``
    (each order's blocks), from which ``crossplay.seat_pairs`` reads each pair of groups. Raises
    ``RayBackendError`` when Ray cannot be reached."""
    played = _play(options, groups, groups, seed, episodes, label, precision)
    if timer is not None:
        timer.tick()
    result = crossplay.SeatFairMatrix(played, played)
    return ComparisonResult(result, crossplay.summarize_seat_fair(result))


# ---------------------------------------------------------------------------------------------------
# status
# ---------------------------------------------------------------------------------------------------


def missing_runs(study: Study, out: Path, state: StudyState) -> list[str]:
    """One line per run whose training study.json records but whose directory is gone (empty: none)."""
    lines = []
    for run in study.runs:
        step = state.steps.get(Step("train", run.name).name, StepRecord())
        path = run_dir(out, run.name)
        if step.recorded_progress and not (path / "config.yaml").is_file():
            lines.append(f"{path}: missing, though study.json records its training as {step.status}")
    return lines


def study_status(out) -> list[dict]:
    """One entry per step: name, status (done / running / partial / blocked / left / to redo), progress, ETA in
    seconds for training steps (from the throughput this study measured, per model kind; None when unknown)."""
    out = Path(out).resolve()
    state = read_state(out)
    if state is None:
        raise StudyError(f"{out}: not a study directory (no {STATE_NAME})")
    study = kept_study(state, out)
    rates = _rates(study, out, state)
    configs, unplanned = {}, {}
    for run in study.runs:  # what a run not started yet will train (the budget and seeds the study keeps)
        try:
            configs[run.name] = run_config(study, run, out, state.budget, state.seeds, state.budget_mode)
        except StudyError as error:  # shown beside the step: `study run` would stop on it
            unplanned[run.name] = str(error)
    entries = []
    for one in study_steps(study):
        name = one.name
        step = state.steps.get(name, StepRecord())
        status = step.status
        entry = {"step": name, "status": status, "wall_s": step.wall_s, "detail": step.reason or "", "eta_s": None}
        path = run_dir(out, one.target)
        if one.kind == "train":
            entry.update(_train_progress(path, configs.get(one.target), rates))
            if status != "done" and entry.pop("finished", False):
                entry["status"] = "done"
            if one.target in unplanned and entry["status"] != "done":
                entry["progress"] = f"{entry['progress']}; cannot go on: {unplanned[one.target]}"
        if status == "done" and entry["status"] == "done" and (problem := _redo_problem(one, study, out, configs)):
            # its result went missing or was damaged since it was done: `study run` does it again (a run is
            # evaluated again, training nothing)
            entry.update(status="to redo", detail=f"{problem}; `ocv2 study run` does it again")
        if status == "running":
            if not DirLock(out).held_elsewhere():
                entry["status"] = "interrupted"
            elif step.ticked is not None:  # wall time is saved per chunk; add the running chunk's so far
                entry["wall_s"] += max(0.0, time.time() - step.ticked)
        if one.kind == "train" and step.recorded_progress and not (path / "config.yaml").is_file():
            entry.update(status="missing", detail=f"{path}: missing, though study.json records the step as {status}")
            entry.pop("progress", None)
        entries.append(entry)
    return entries


def _redo_problem(step: Step, study: Study, out: Path, configs: dict) -> str | None:
    """``result_problem`` of a step study.json records as done, where ``configs`` plans every run it compares
    (a run that cannot be planned is shown as such beside its train step)."""
    compared = next((c.runs for c in study.comparisons if c.name == step.target), ()) if step.kind == "compare" else ()
    if any(name not in configs for name in compared):
        return None
    return result_problem(step, study, out, configs)


def _rates(study: Study, out: Path, state: StudyState) -> dict:
    """Measured env steps per second of population training, per model kind, from this study's runs."""
    totals: dict = {}
    for run in study.runs:
        step = state.steps.get(Step("train", run.name).name, StepRecord())
        path = run_dir(out, run.name)
        if not (path / "config.yaml").is_file() or not step.wall_s:
            continue
        config = RunDir(path).load_config()
        rows = RunDir(path).read_metrics()
        done = max((int(float(r["update"])) for r in rows), default=0)
        steps = done * config.ppo.steps_per_update * config.population.num_seeds
        kind = config.model.kind
        seen = totals.setdefault(kind, [0.0, 0.0])
        seen[0] += steps
        seen[1] += step.wall_s
    return {kind: steps / wall for kind, (steps, wall) in totals.items() if wall > 0 and steps > 0}


def _train_progress(path: Path, planned, rates: dict) -> dict:
    if (path / "config.yaml").is_file():
        run = RunDir(path)
        config, manifest = run.load_config(), run.read_manifest()
    elif planned is not None:
        config, manifest = planned, {"status": "not started"}
    else:
        return {"progress": "not started"}
    update = int(manifest.get("update") or 0)
    total = config.ppo.num_updates
    remaining = (total - update) * config.ppo.steps_per_update * config.population.num_seeds
    rate = rates.get(config.model.kind)
    return {
        "progress": f"update {update}/{total} ({manifest.get('status', 'created')})",
        "eta_s": remaining / rate if rate else (0.0 if not remaining else None),
        "finished": manifest.get("status") != "not started" and run_finished(path),
    }

"""Study files: many population runs and the comparisons between them, as one typed, validated object.

A study file is YAML::

    study: table1_coord_ring            # a name (the report's title)
    description: ...                    # optional, printed at the top of the report
    set: [run.num_checkpoints=11]       # optional overrides for every run
    runs:
      - name: sp                        # unique; the run's folder is STUDY_DIR/runs/<name>
        config: ../paper/classic_coord_ring_sp.yaml   # relative to the study file
        set: [population.seed=0]        # optional overrides for this run
        partners_from: sp               # FCP only: the pools come from this earlier run of the study
        paper:                          # optional: the paper's numbers for this row
          source: "Table 1, Coordination Ring, standard"
          sp: [214, 8]                  # mean or [mean, std]
          xp: [96, 72]
          gap: 118
    over_training: [sp]                 # optional: in-run cross-play of every kept snapshot of these runs
    comparisons:
      - name: coord_ring                # cross-run cross-play between these runs, both seat orders
        runs: [sp, sa]
        human_proxy: true               # also the BC human proxy of the layout, in both seats

``load_study`` reads and checks it; every error is one line naming the file and the entry at fault.
``run_config`` turns a run into the ``population.config.Config`` it trains with at a budget fraction and seed
count; the budget stops every run after that fraction of its schedule (truncate, the default) or scales
``total_timesteps`` and ``rew_shaping_horizon`` (compress; the LR schedule follows the
number of updates by itself), of the FCP partner stage too.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from population.config import Config, ConfigError, load_config, read_yaml
from population.config.errors import SET_PREFIX
from population.config.parse import CONFIG_MARKS, mixed_file_problem

STUDY_KEYS = ("study", "description", "set", "runs", "over_training", "comparisons")
RUN_KEYS = ("name", "config", "set", "partners_from", "paper")
PAPER_KEYS = ("source", "sp", "xp", "gap", "note")
COMPARISON_KEYS = ("name", "runs", "human_proxy")
#: A study, run or comparison name (a folder name): matched whole, so no trailing newline slips through ``$``.
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
NAME_RULE = "1-64 letters, digits, _ . -, the first a letter or digit"
#: The FCP settings ``partners_from`` gives a run: set beside it, they were dropped without a word.
PARTNER_KEYS = ("population.fcp.pool", "population.fcp.partners", "population.fcp.partner_seeds")
#: Names a run or comparison may not take: the folders of pictures and archives ``cluster.study.pack`` leaves out.
RESERVED_NAMES = ("archive", "gifs", "plots")


class StudyError(ValueError):
    """A study file or study directory that cannot be used; the message is one line naming the entry."""


@dataclasses.dataclass(frozen=True)
class PaperValue:
    """A number of the paper's tables: its mean and, where the paper gives one, its standard deviation."""

    mean: float
    std: float | None = None


@dataclasses.dataclass(frozen=True)
class PaperNumbers:
    """One row of the paper's tables: where it comes from and its SP / XP / gap (each optional)."""

    source: str
    sp: PaperValue | None = None
    xp: PaperValue | None = None
    gap: PaperValue | None = None
    note: str = ""


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One run of a study: its name, its config file, the overrides applied to it, the earlier run of the study
    whose SP seeds it takes as FCP partners (``partners_from``) and the paper's numbers to set beside it."""

    name: str
    config: Path  # absolute
    overrides: tuple[str, ...] = ()  # the study file's, the run's, then ``ocv2 study run --set``
    partners_from: str | None = None
    paper: PaperNumbers | None = None
    #: Where each override came from, as errors name it ("set", "run 'sp'.set", "--set"); () for all "--set".
    sources: tuple[str, ...] = ()

    def source_labels(self) -> tuple[str, ...]:
        """Each override's source, in order (a RunSpec made without ``sources``: every one "--set")."""
        return self.sources or ("--set",) * len(self.overrides)

    def override_sources(self) -> dict[str, str]:
        """Each override's source; an override given twice goes by the later one, which wins."""
        return dict(zip(self.overrides, self.source_labels(), strict=True))


@dataclasses.dataclass(frozen=True)
class Comparison:
    """A cross-play step between runs of a study (every pair of their seeds, both seat orders), optionally with
    the human proxy as one more row."""

    name: str
    runs: tuple[str, ...]
    human_proxy: bool = False


@dataclasses.dataclass(frozen=True)
class Study:
    """A parsed study file: its runs, comparisons and over-training cross-plays, and the file's data (``raw``),
    which the study directory keeps so that a later run of the directory needs no file."""

    name: str
    path: Path
    description: str
    runs: tuple[RunSpec, ...]
    comparisons: tuple[Comparison, ...]
    over_training: tuple[str, ...]
    raw: Mapping  # the file's data, kept in the study directory
    where: str = ""  # what errors name, when the data is not read from ``path`` (a study directory's study.json)

    @property
    def origin(self) -> str:
        """Where the study's data was read from, for messages."""
        return self.where or str(self.path)

    def run(self, name: str) -> RunSpec:
        """The run named ``name`` (``StopIteration`` when there is none; the parser checks names)."""
        return next(r for r in self.runs if r.name == name)


# ---------------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------------


def load_study(path) -> Study:
    """Read and check a study file (every config it names is loaded once, so a typo fails here). A study
    directory, or its study.json, is refused (``cluster.study.runner.continue_hint`` says how to continue one)."""
    path = Path(path).resolve()
    if is_study_directory(path):
        raise StudyError(f"{path}: is a study directory (or its study.json), not a study file")
    try:
        raw = read_yaml(str(path))
    except ConfigError as error:  # read_yaml names what it reads a config file
        raise StudyError(str(error).replace("config file", "study file")) from None
    return check_runs(parse_study(raw, path))


#: The file a study directory keeps its state in (``cluster.study.state.StudyState``).
STATE_NAME = "study.json"


def is_study_directory(path: Path) -> bool:
    """Whether ``path`` is a study directory or its study.json: given where a study file belongs."""
    state_file = path / STATE_NAME if path.is_dir() else path
    return state_file.name == STATE_NAME and state_file.is_file()


def default_out(study: Study) -> Path:
    """The study directory ``ocv2 study run`` uses without ``--out``: ``studies/<study name>``."""
    return Path("studies") / study.name


def check_runs(study: Study) -> Study:
    """``study``, once each run's config has loaded with its overrides (at budget 1, the seed count as
    written, in its default study directory); the first that does not is a ``StudyError`` naming the run."""
    for run in study.runs:
        run_config(study, run, default_out(study), budget=1.0, seeds=None)
    return study


def parse_study(raw: Any, path: Path) -> Study:
    """The ``Study`` a study file's data ``raw`` (read from ``path``) describes, its configs not loaded
    (``check_runs`` loads them). Raises ``StudyError`` naming the entry at fault."""
    where = str(path)
    if not isinstance(raw, Mapping):
        raise StudyError(f"{where}: a study file is a mapping with keys {', '.join(STUDY_KEYS)}")
    mixed = mixed_file_problem(raw)
    if mixed is not None:
        raise StudyError(f"{where}: {mixed}")
    if "study" not in raw and set(CONFIG_MARKS) & set(raw):
        raise StudyError(
            f"{where}: is an experiment config, not a study file (no 'study' key); run it with `ocv2 train`"
        )
    _unknown(where, "", raw, STUDY_KEYS)
    name = raw.get("study")
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise StudyError(f"{where}: study: expected a name ({NAME_RULE}), got {name!r}")
    shared = _overrides(where, "set", raw.get("set"))
    runs_raw = raw.get("runs")
    if not isinstance(runs_raw, list) or not runs_raw:
        raise StudyError(f"{where}: runs: expected a non-empty list of runs")
    runs: list[RunSpec] = []
    for index, entry in enumerate(runs_raw):
        runs.append(_parse_run(where, index, entry, path.parent, shared, [r.name for r in runs]))
    names = [r.name for r in runs]
    # A key left empty (``comparisons:``) is none; any other value that is not a list is refused, not read as empty.
    over = [] if raw.get("over_training") is None else raw["over_training"]
    if not isinstance(over, list) or not all(isinstance(n, str) for n in over):
        raise StudyError(f"{where}: over_training: expected a list of run names")
    for index, name_ in enumerate(over):
        _known_run(where, "over_training", name_, names)
        if name_ in over[:index]:
            raise StudyError(f"{where}: over_training: names run {name_!r} twice")
    comparisons: list[Comparison] = []
    listed = [] if raw.get("comparisons") is None else raw["comparisons"]
    if not isinstance(listed, list):
        raise StudyError(f"{where}: comparisons: expected a list of comparisons, got {type(listed).__name__}")
    for index, entry in enumerate(listed):
        comparisons.append(_parse_comparison(where, index, entry, names, [c.name for c in comparisons]))
    description = "" if raw.get("description") is None else raw["description"]
    if not isinstance(description, str):
        raise StudyError(f"{where}: description: expected text")
    return Study(name, path, description.strip(), tuple(runs), tuple(comparisons), tuple(over), raw)


def _parse_run(where: str, index: int, entry, base: Path, shared: tuple[str, ...], earlier: list[str]) -> RunSpec:
    name, label = _named_entry(where, "runs", "run", index, entry, RUN_KEYS, earlier)
    config = entry.get("config")
    if not isinstance(config, str) or not config:
        raise StudyError(f"{where}: {label}.config: expected a config file path")
    try:
        config_path = (base / config).resolve()
    except RuntimeError as error:  # a symbolic link loop (Python 3.11-3.12; 3.13 leaves it to is_file below)
        raise StudyError(
            f"{where}: {label}.config: {config}: its symbolic links cannot be followed ({error})"
        ) from None
    if config_path.is_dir():
        raise StudyError(f"{where}: {label}.config: {config} is a folder (at {config_path}); name a config file")
    if config_path.exists() and not config_path.is_file():
        raise StudyError(f"{where}: {label}.config: {config} is not a regular file (a device or pipe); name a config")
    if not config_path.is_file():
        raise StudyError(f"{where}: {label}.config: no such config file {config} (looked for {config_path})")
    partners = entry.get("partners_from")
    if partners is not None:
        if not isinstance(partners, str):
            raise StudyError(f"{where}: {label}.partners_from: expected a run name")
        _known_run(where, f"{label}.partners_from", partners, earlier, before=True)
    paper = _parse_paper(where, label, entry.get("paper"))
    own = _overrides(where, f"{label}.set", entry.get("set"))
    sources = ("set",) * len(shared) + (f"{label}.set",) * len(own)
    if partners is not None:
        for item, source in zip(shared + own, sources, strict=True):
            key = item.split("=", 1)[0].strip()
            if key in PARTNER_KEYS:
                raise StudyError(
                    f"{where}: {source}: {item!r} and {label}.partners_from both give {key}; partners_from sets "
                    f"the pool (shared), the partner run and its seeds: leave {key} out"
                )
    return RunSpec(name, config_path, shared + own, partners, paper, sources)


def _parse_paper(where: str, label: str, raw) -> PaperNumbers | None:
    if raw is None:
        return None
    if not isinstance(raw, Mapping):
        raise StudyError(f"{where}: {label}.paper: expected a mapping with keys {', '.join(PAPER_KEYS)}")
    _unknown(where, f"{label}.paper: ", raw, PAPER_KEYS)
    source = raw.get("source")
    if not isinstance(source, str) or not source.strip():
        raise StudyError(f"{where}: {label}.paper.source: say which table and row the numbers come from")
    values = {key: _paper_value(where, f"{label}.paper.{key}", raw.get(key)) for key in ("sp", "xp", "gap")}
    note = raw.get("note")
    note = "" if note is None else note  # false or [] is no text: refused below, not read as an empty note
    if not isinstance(note, str):
        raise StudyError(f"{where}: {label}.paper.note: expected text")
    return PaperNumbers(source.strip(), note=note.strip(), **values)


def _paper_value(where: str, key: str, raw) -> PaperValue | None:
    if raw is None:
        return None
    items = raw if isinstance(raw, list) else [raw]
    if not 1 <= len(items) <= 2 or not all(_finite_number(v) for v in items):
        raise StudyError(f"{where}: {key}: expected a number or [mean, std], got {raw!r}")
    if len(items) == 2 and items[1] < 0:
        raise StudyError(f"{where}: {key}: the std must be >= 0, got {items[1]}")
    return PaperValue(float(items[0]), float(items[1]) if len(items) == 2 else None)


def _parse_comparison(where: str, index: int, entry, names: list[str], earlier: list[str]) -> Comparison:
    name, label = _named_entry(where, "comparisons", "comparison", index, entry, COMPARISON_KEYS, earlier)
    runs = entry.get("runs")
    if not isinstance(runs, list) or not all(isinstance(r, str) for r in runs):
        raise StudyError(f"{where}: {label}.runs: expected a list of run names")
    for run in runs:
        _known_run(where, f"{label}.runs", run, names)
    if len(set(runs)) != len(runs):
        raise StudyError(f"{where}: {label}.runs: names a run twice")
    human = entry.get("human_proxy", False)
    if not isinstance(human, bool):
        raise StudyError(f"{where}: {label}.human_proxy: expected true or false, got {human!r}")
    if len(runs) + human < 2:
        raise StudyError(f"{where}: {label}: needs two runs, or one run and human_proxy: true")
    if name in names:  # their matrices and heatmaps would be written to the same files
        raise StudyError(f"{where}: {label}: a run has this name too; give the comparison another name")
    return Comparison(name, tuple(runs), human)


def _named_entry(where: str, section: str, noun: str, index: int, entry, keys, earlier: list[str]) -> tuple[str, str]:
    """The name of entry ``index`` of a list of named mappings (``runs``, ``comparisons``) and the label its
    errors go by; checks its keys and that no earlier entry has its name."""
    label = f"{section}[{index}]"
    if not isinstance(entry, Mapping):
        raise StudyError(f"{where}: {label}: expected a mapping with keys {', '.join(keys)}")
    name = entry.get("name")
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise StudyError(f"{where}: {label}.name: expected a name ({NAME_RULE}), got {name!r}")
    if name in RESERVED_NAMES:
        raise StudyError(
            f"{where}: {label}.name: {name!r} names the folders a pack leaves out ({', '.join(RESERVED_NAMES)}), "
            f"so a {noun} of that name would not be packed; choose another"
        )
    label = f"{noun} {name!r}"
    _unknown(where, f"{label}: ", entry, keys)
    folded = [e.casefold() for e in earlier]  # "sp" and "SP" would share one folder on a case-insensitive disk
    if name.casefold() in folded:
        index = folded.index(name.casefold())
        case = "" if earlier[index] == name else f" as {earlier[index]!r}: names differing only in case share a folder"
        raise StudyError(f"{where}: {label}: duplicate {noun} name ({section}[{index}] has it too{case})")
    return name, label


def _unknown(where: str, label: str, raw: Mapping, keys) -> None:
    for key in raw:
        if key not in keys:
            close = difflib.get_close_matches(str(key), keys, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else f"; valid keys are {', '.join(keys)}"
            raise StudyError(f"{where}: {label}unknown key {key!r}{hint}")


def _known_run(where: str, label: str, name: str, names: list[str], before: bool = False) -> None:
    if name not in names:
        close = difflib.get_close_matches(name, names, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        what = "no earlier run" if before else "no run"
        raise StudyError(f"{where}: {label}: {what} is named {name!r}{hint}")


def _overrides(where: str, key: str, raw) -> tuple[str, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list) or not all(isinstance(item, str) and "=" in item for item in raw):
        raise StudyError(f"{where}: {key}: expected a list of section.key=value overrides")
    return tuple(raw)


def _finite_number(value) -> bool:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an integer beyond float's range (a study.json holds what JSON can)
        return False


# ---------------------------------------------------------------------------------------------------
# runs at a budget
# ---------------------------------------------------------------------------------------------------


def run_dir(out: Path, name: str) -> Path:
    """Where run ``name`` of study directory ``out`` lies: ``out/runs/<name>``."""
    return Path(out) / "runs" / name


def comparison_dir(out: Path, name: str) -> Path:
    """Where comparison ``name`` of study directory ``out`` writes: ``out/comparisons/<name>``."""
    return Path(out) / "comparisons" / name


def with_overrides(study: Study, overrides: Sequence[str]) -> Study:
    """``study`` with ``overrides`` (``ocv2 study run --set``) applied to every run after the study file's
    own, e.g. ``eval.episodes=8`` for a quick pilot of the whole pipeline (not checked: ``check_runs``)."""
    if not overrides:
        return study
    runs = tuple(
        dataclasses.replace(
            r,
            overrides=(*r.overrides, *overrides),
            sources=(*r.source_labels(), *("--set",) * len(overrides)),
        )
        for r in study.runs
    )
    return dataclasses.replace(study, runs=runs)


BUDGET_MODES = ("truncate", "compress")


#: Overrides every study run starts from; the study file's ``set``, the run's ``set`` and ``ocv2 study run --set``
#: come after them and win. The report reads each run's cross-play scores (``xp/summary.json``, ``xp/matrix.csv``,
#: under 1 KB; the per-episode returns and start recipes are in ``xp/episodes.csv``), never its XP archive, which
#: keeps every transition of every scored episode: 7.4 GB copied from the device and written for a 10-seed, 500-episode Coordination Ring matrix,
#: 11-12 GB on the V2 layouts. ``set: [archive.xp=true]`` asks for it (docs/studies.md).
STUDY_DEFAULTS = ("archive.xp=false",)


def run_config(
    study: Study, run: RunSpec, out: Path, budget: float, seeds: int | None, budget_mode: str = "truncate"
) -> Config:
    """The config ``run`` trains with in study directory ``out`` at ``budget`` (a fraction of
    ``total_timesteps``, applied as ``budget_mode``: see ``budget_overrides``) and ``seeds`` (None: the
    config's own)."""
    where = f"{study.origin}: run {run.name!r}"
    sources = run.override_sources()
    overrides = [*STUDY_DEFAULTS, *run.overrides]
    if seeds is not None:
        overrides.append(f"population.num_seeds={seeds}")
        sources[overrides[-1]] = "--seeds"
    if run.partners_from is not None:
        partner = study.run(run.partners_from)
        partner_seeds = run_config(study, partner, out, budget, seeds, budget_mode).population.num_seeds
        given = [
            "population.fcp.pool=shared",
            f"population.fcp.partners={run_dir(out, partner.name)}",
            f"population.fcp.partner_seeds={partner_seeds}",
        ]
        overrides += given
        sources |= dict.fromkeys(given, f"run {run.name!r}.partners_from")
    base = _load(where, run.config, overrides, sources)
    if run.partners_from is not None and base.population.method != "fcp":
        raise StudyError(f"{where}.partners_from: only FCP runs take partners (this run is {base.population.method})")
    scaled = budget_overrides(base, budget, budget_mode)
    overrides += scaled
    sources |= dict.fromkeys(scaled, f"--budget {budget:g}")
    return _load(where if budget == 1.0 else f"{where} at --budget {budget:g}", run.config, overrides, sources)


def budget_overrides(config: Config, budget: float, mode: str = "truncate") -> list[str]:
    """Overrides that make a run train ``budget`` x its env steps (at least one update).

    ``truncate``: the config's schedule (LR warm-up and decay, reward-shaping horizon, SA iterations) as
    written, stopped after ``budget`` of its steps: the first part of the full run, whose snapshots are
    that run's intermediate checkpoints. ``compress``: the whole schedule squeezed into the shorter run
    (warm-up, decay and shaping end ``budget`` times sooner) -- how studies ran before truncation existed.
    """
    if mode not in BUDGET_MODES:
        raise StudyError(f"--budget-mode: expected one of {', '.join(BUDGET_MODES)}, got {mode!r}")
    if budget == 1.0:
        return []
    if mode == "truncate" and budget > 1:
        raise StudyError(
            f"--budget {budget:g}: --budget-mode truncate stops each schedule early and cannot run past its end; "
            "give --budget 1 or less, or --budget-mode compress to stretch the schedules over more env steps"
        )

    def scaled(prefix: str, ppo) -> list[str]:
        steps = max(ppo.steps_per_update, round(ppo.total_timesteps * budget))
        if mode == "truncate":
            return [f"{prefix}.total_timesteps={steps}", f"{prefix}.schedule_timesteps={ppo.total_timesteps}"]
        return [
            f"{prefix}.total_timesteps={steps}",
            f"{prefix}.rew_shaping_horizon={round(ppo.rew_shaping_horizon * budget)}",
        ]

    out = scaled("ppo", config.ppo)
    fcp = config.population.fcp
    if config.population.trains_partners and fcp.partner_ppo is not None:
        out += scaled("population.fcp.partner_ppo", fcp.partner_ppo)
    return out


def _load(where: str, path: Path, overrides: list[str], sources: Mapping[str, str]) -> Config:
    try:
        return load_config(path, overrides)
    except ConfigError as error:
        raise StudyError(f"{where}: {_named_by_source(error, sources)}") from None


def _named_by_source(error: ConfigError, sources: Mapping[str, str]) -> ConfigError:
    """``error`` with each problem of an override the study file gave named after the file's key that gave it
    (``set: ppo.lr=abc: ...``, ``run 'sp'.set: ...``) rather than ``--set``, which the user did not type."""

    def named(problem: str) -> str:
        for item, source in sources.items():
            given = f"{SET_PREFIX}{item}"
            if source != "--set" and (problem == given or problem.startswith(f"{given}: ")):
                return f"{source}: {item}{problem[len(given) :]}"
        return problem

    return ConfigError([named(problem) for problem in error.problems])

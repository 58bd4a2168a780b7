"""A study directory's record (study.json) as typed objects: what the study is, the options it keeps, each step.

study.json is the one file that says what a study directory holds and how far it got; a resumed study, ``ocv2
study status`` and ``ocv2 study report`` all start from it. ``StudyState.from_json`` checks every field once, where
the file is read (a damaged file is one line naming the file and the field, never a KeyError deep in a step), and
the rest of the study code works with attributes. ``to_json`` writes the same shape the file has always had, so
directories and packs made before these classes existed read and resume unchanged.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from cluster.study.spec import BUDGET_MODES, NAME, StudyError

#: The states a step may be in.
STEP_STATES = ("left", "running", "done", "blocked")
_RESTORE = "restore it from a backup or a pack of this study (ocv2 study pack)"
#: Optional step fields that are times or durations (seconds).
_STEP_NUMBERS = ("started", "ticked", "finished")
#: Optional step fields that are text.
_STEP_TEXTS = ("reason", "backend")
#: What a finished step records of its result (``update``: a training step's last update; ``snapshots``: how many
#: snapshots an over-training step played).
_STEP_RESULTS = ("update", "snapshots")


@dataclasses.dataclass
class StepRecord:
    """One step's progress. Mutable: the runner updates it as the step starts, ticks and ends, and saves it."""

    status: str = "left"
    wall_s: float = 0.0  # wall time spent on the step so far, over every attempt
    started: float | None = None  # time.time() when the current (or last) attempt started
    ticked: float | None = None  # ... when its wall time was last added to (lets a status add the time since)
    finished: float | None = None
    reason: str | None = None  # why the step is blocked
    backend: str | None = None  # the backend that last ran it (steps recorded before it was kept have none)
    results: dict = dataclasses.field(default_factory=dict)  # what the step returned (_STEP_RESULTS)

    @property
    def recorded_progress(self) -> bool:
        """study.json says the step has made something (done, or an update reached): its run directory must exist.
        A step that failed before it made one (a Ray connection, its SA archives) has not."""
        return self.status == "done" or bool(self.results.get("update"))

    def update(self, **changes) -> None:
        """Set fields by name; a step's results (``update=...``) go to ``results``."""
        for key, value in changes.items():
            if key in _FIELDS:
                setattr(self, key, value)
            else:
                self.results[key] = value

    @property
    def done(self) -> bool:
        """Whether the step has finished (its result still has to match its inputs: ``result_problem``)."""
        return self.status == "done"

    def to_json(self) -> dict:
        """The step's entry in study.json: status and wall time always, the rest when set."""
        data = {"status": self.status, "wall_s": self.wall_s}
        data.update({k: getattr(self, k) for k in (*_STEP_NUMBERS, *_STEP_TEXTS) if getattr(self, k) is not None})
        return {**data, **self.results}

    @classmethod
    def from_json(cls, data, field: str, path: Path) -> StepRecord:
        """Step entry ``data`` (``field``: its name in study.json, for errors), checked; StudyError names the field."""
        if not isinstance(data, dict):
            raise _bad(path, field, "an object", data)
        status = data.get("status", "left")
        if status not in STEP_STATES:
            raise _bad(path, f"{field}.status", " / ".join(STEP_STATES), status)
        for key in ("wall_s", *_STEP_NUMBERS):
            if key in data and not is_number(data[key]):
                raise _bad(path, f"{field}.{key}", "a number", data[key])
        for key in _STEP_TEXTS:
            if key in data and not isinstance(data[key], str):
                raise _bad(path, f"{field}.{key}", "text", data[key])
        return cls(
            status=status,
            wall_s=float(data.get("wall_s", 0.0)),
            **{key: data.get(key) for key in (*_STEP_NUMBERS, *_STEP_TEXTS)},
            results={k: v for k, v in data.items() if k not in _FIELDS},  # kept as they were: nothing is lost
        )


_FIELDS = {f.name for f in dataclasses.fields(StepRecord)} - {"results"}


@dataclasses.dataclass
class StudyState:
    """study.json: the study (its name and the study file's data as it was when the directory was made or last
    run), the options the directory keeps (budget, budget mode, seed count, ``--set`` overrides), the backend and
    source of the last run, every step's record and the report's paths."""

    study: str
    spec: dict
    budget: float = 1.0
    budget_mode: str = "compress"  # directories from before --budget-mode existed compressed
    seeds: int | None = None
    overrides: tuple[str, ...] = ()  # "set" in the file
    source: str | None = None
    backend: str | None = None
    created: float | None = None
    report: dict | None = None
    steps: dict[str, StepRecord] = dataclasses.field(default_factory=dict)
    # ``--extend``: each raise of the budget, {"from": old budget, "to": new budget, "at": unix time}
    extensions: list[dict] = dataclasses.field(default_factory=list)
    extra: dict = dataclasses.field(default_factory=dict)  # fields this version does not know, kept as they were

    def step(self, name: str) -> StepRecord:
        """Step ``name``'s record, created "left" with no wall time when it has none."""
        return self.steps.setdefault(name, StepRecord())

    def to_json(self) -> dict:
        """study.json's content, in the shape the file has always had (unknown fields written back as read)."""
        data = {
            "study": self.study,
            "budget": self.budget,
            "budget_mode": self.budget_mode,
            "seeds": self.seeds,
            "set": list(self.overrides),
            "steps": {name: step.to_json() for name, step in self.steps.items()},
        }
        for key in ("created", "source", "backend", "report"):
            if getattr(self, key) is not None:
                data[key] = getattr(self, key)
        if self.extensions:
            data["extensions"] = self.extensions
        return {**self.extra, **data, "spec": self.spec}

    @classmethod
    def from_json(cls, data, path: Path) -> StudyState:
        """``data`` (a parsed study.json) checked field by field; a StudyError names the file and the field."""
        if not isinstance(data, dict):
            raise StudyError(f"{path}: holds a JSON {type(data).__name__}, not an object; {_RESTORE}")
        study = data.get("study")
        if not isinstance(study, str) or not NAME.fullmatch(study):
            raise _bad(path, "study", "the study's name", study)
        if not isinstance(data.get("spec"), dict):
            raise _bad(path, "spec", "the study file's data (an object)", data.get("spec", "nothing"))
        budget = data.get("budget")
        if not is_number(budget) or not 0 < budget <= 100:
            raise _bad(path, "budget", "a number in (0, 100]", budget)
        mode = data.get("budget_mode", "compress")
        if mode not in BUDGET_MODES:
            raise _bad(path, "budget_mode", " or ".join(BUDGET_MODES), mode)
        seeds = data.get("seeds")
        if seeds is not None and (not isinstance(seeds, int) or isinstance(seeds, bool) or seeds < 1):
            raise _bad(path, "seeds", "null or a positive integer", seeds)
        overrides = data.get("set", [])  # a study directory from before --set has none
        if not isinstance(overrides, list) or not all(isinstance(o, str) and "=" in o for o in overrides):
            raise _bad(path, "set", "a list of section.key=value overrides", overrides)
        for key in ("source", "backend"):
            if key in data and not isinstance(data[key], str):
                raise _bad(path, key, "text", data[key])
        if "created" in data and not is_number(data["created"]):
            raise _bad(path, "created", "a number", data["created"])
        if "report" in data and not isinstance(data["report"], dict):
            raise _bad(path, "report", "an object", data["report"])
        steps = data.get("steps", {})
        if not isinstance(steps, dict):
            raise _bad(path, "steps", "an object of steps", steps)
        extensions = data.get("extensions", [])
        if not isinstance(extensions, list) or not all(
            isinstance(e, dict) and is_number(e.get("from")) and is_number(e.get("to")) for e in extensions
        ):
            raise _bad(path, "extensions", 'a list of {"from": budget, "to": budget} objects', extensions)
        known = (
            *("study", "spec", "budget", "budget_mode", "seeds", "set", "source", "backend", "created", "report"),
            "extensions",
        )
        return cls(
            study=study,
            spec=data["spec"],
            budget=budget,
            budget_mode=mode,
            seeds=seeds,
            overrides=tuple(overrides),
            source=data.get("source"),
            backend=data.get("backend"),
            created=data.get("created"),
            report=data.get("report"),
            steps={name: StepRecord.from_json(step, f"steps[{name!r}]", path) for name, step in steps.items()},
            extensions=extensions,
            extra={k: v for k, v in data.items() if k not in (*known, "steps")},
        )


def is_number(value) -> bool:
    """A finite int or float (not a bool): what study.json's numbers must be."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an integer of hundreds of digits
        return False


def _bad(path: Path, field: str, expected: str, value) -> StudyError:
    shown = repr(value)
    shown = shown if len(shown) <= 60 else shown[:57] + "..."
    return StudyError(f"{path}: {field}: expected {expected}, got {shown}; {_RESTORE}")

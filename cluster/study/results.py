"""Reading a study step's result files (a run's cross-play summary, a comparison's, an over-training point),
and comparing a trained run's config with what the study asks for it: one rule for the runner, which decides
from them whether a step is done or a run may go on, and the report, which shows them."""

from __future__ import annotations

from pathlib import Path

from ocv2 import boundedjson
from population.config import Config


def read_result(path: Path, required: tuple[str, ...] = ()) -> tuple[dict, str | None]:
    """A step's result file as (data, None), or ({}, why it cannot be used): missing, unreadable, not a JSON
    object or without the ``required`` keys (a file another command wrote over it)."""
    try:
        data = boundedjson.loads(Path(path).read_text())
    except FileNotFoundError:
        return {}, f"{path} is missing"
    except (OSError, ValueError) as error:  # ValueError: not JSON (UnicodeDecodeError, JSONDecodeError, too deep)
        return {}, f"{path} is unreadable ({error})"
    if not isinstance(data, dict):
        return {}, f"{path} holds a JSON {type(data).__name__}, not a result"
    missing = [key for key in required if key not in data]
    if missing:
        return {}, f"{path} is not a result of this step (no {', '.join(missing)})"
    return data, None


#: Config keys compared between a trained run and what the study asks for it: the training settings the
#: fingerprint covers and eval.episodes, which the reported cross-play used. Where the partners of an FCP
#: run lie is left out (the study directory may have moved), as are cluster, archive and the checkpoint
#: cadence, which may change between drivers.
COMPARED_RUN_KEYS = ("run.precision", "run.deterministic", "eval.episodes")
_NOT_COMPARED = ("population.fcp.partners",)


def evaluation_problem(path: Path, summary: dict, config: Config) -> str | None:
    """Why a run's cross-play ``summary`` (read from ``path``) is not the evaluation of the run's ``config``:
    made with another number of episodes per pair (``ocv2 xp RUN_DIR --episodes N`` rewrites it in place) or of
    another number of policies; None when it is. Every summary ocv2 has written carries both keys. Nothing else
    varies: the in-run form plays every ordered pair (both seat orders) of the final policies at
    ``run.precision``."""
    made = (summary.get("episodes_per_pair"), summary.get("num_policies"))
    asked = (config.eval.episodes, config.population.num_seeds)
    if made == asked:
        return None
    return (
        f"{path} was made with {made[0]} episodes per pair of {made[1]} policies, not the run's eval.episodes "
        f"{asked[0]} of its {asked[1]} seeds (`ocv2 xp RUN_DIR --episodes N` rewrites it)"
    )


def compared_settings(config: Config) -> dict:
    """The dotted keys and values of ``config`` that ``config_differences`` compares."""
    every = config.flat()
    flat = {key: value for key, value in every.items() if key.split(".")[0] in ("env", "model", "ppo", "population")}
    flat.update({dotted: every[dotted] for dotted in COMPARED_RUN_KEYS})
    for dotted in _NOT_COMPARED:
        flat.pop(dotted, None)
    return flat


def config_differences(trained: Config, planned: Config) -> list[str]:
    """How a run's config ``trained`` differs from ``planned`` in what matters to its numbers ("ppo.lr: 0.0004
    in the run, 0.01 now"), sorted by key; empty when nothing does."""
    before, now = compared_settings(trained), compared_settings(planned)
    return [
        f"{key}: {_shown(before.get(key))} in the run, {_shown(now.get(key))} now"
        for key in sorted(set(before) | set(now))
        if before.get(key) != now.get(key)
    ]


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."

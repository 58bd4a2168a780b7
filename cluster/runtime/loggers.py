"""Experiment loggers people already use: TensorBoard and Weights & Biases, fed by the training hook.

Each logger gets every row of ``metrics.csv`` as it is merged (one row per seed and update), then the
cross-play summary and heatmap after evaluation. Both are optional extras (``ocv2[tensorboard]``,
``ocv2[wandb]``); asking for one that is not installed is a ``MissingExtraError`` before anything runs.

* ``tensorboard``: event files in ``RUN_DIR/tensorboard/`` (``tensorboard --logdir RUN_DIR``). Scalars
  are tagged ``<metric>/seed_<i>`` (``scalar_tag``) so each metric's chart shows every seed, plotted against
  environment steps; cross-play numbers are ``xp/<name>`` and the heatmap an image ``xp/heatmap``.
* ``wandb``: one W&B run per run directory (its id is the run directory's name, so a resumed run
  continues the same W&B run), files under ``RUN_DIR/wandb/``; project from ``$WANDB_PROJECT``
  (default ``ocv2``). ``WANDB_MODE=offline`` works without a network.
"""

from __future__ import annotations

import importlib
import math
import os
import re
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np
from PIL import Image

from cluster.runtime.rundir import MetricsRow
from population.config import Config


class MissingExtraError(RuntimeError):
    """An optional dependency that the requested feature needs is not installed."""


class LoggerSetupError(MissingExtraError):
    """A logger's package is installed but cannot log yet (W&B without an API key): said before a run starts."""


class MetricsLogger(Protocol):
    def log_rows(self, rows: Sequence[MetricsRow]) -> None:
        """The rows a chunk added to metrics.csv."""

    def log_xp(self, summary: Mapping, heatmap: Path | None) -> None:
        """The cross-play summary (xp/summary.json) and heatmap image after evaluation."""

    def close(self) -> None: ...


def require(module: str, extra: str, feature: str):
    """Import ``module`` or raise a one-line ``MissingExtraError`` naming the extra to install."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(f"{feature} needs {module}: pip install 'ocv2[{extra}]'") from None


def measurements(row: MetricsRow) -> dict[str, float]:
    """The measured values of a metrics row (columns without a finite value left out)."""
    return {key: value for key, value in row.values.items() if math.isfinite(value)}


def scalar_tag(name: str, seed) -> str:
    """``<metric>/seed_<i>``, with characters TensorBoard does not allow in tags (the ``+`` of recipe
    columns such as ``return_recipe_0+0+1``) replaced by ``_``."""
    return re.sub(r"[^\w./-]", "_", f"{name}/seed_{int(float(seed))}")


def xp_scalars(summary: Mapping) -> dict[str, float]:
    """The top-level numbers of a cross-play summary (sp_mean, xp_mean, gap, ...)."""
    return {
        k: float(v)
        for k, v in summary.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))
    }


def _image(path: Path | None) -> np.ndarray | None:
    if path is None or not Path(path).is_file():
        return None
    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"))


class TensorBoardLogger:
    package, extra = "tensorboardX", "tensorboard"  # what it imports, and the extra that installs it
    about = "event files in RUN_DIR/tensorboard/"  # where it logs, for --logger's help

    def __init__(self, run_dir: Path, config: Config):
        tensorboardx = require(self.package, self.extra, "--logger tensorboard")
        self.writer = tensorboardx.SummaryWriter(logdir=str(Path(run_dir) / "tensorboard"))
        self.steps_per_update = config.ppo.steps_per_update
        self.last_step = 0

    def log_rows(self, rows: Sequence[MetricsRow]) -> None:
        for row in rows:
            self.last_step = max(self.last_step, row.env_steps)
            for name, value in measurements(row).items():
                self.writer.add_scalar(scalar_tag(name, row.seed), value, global_step=row.env_steps)
        self.writer.flush()

    def log_xp(self, summary: Mapping, heatmap: Path | None) -> None:
        for name, value in xp_scalars(summary).items():
            self.writer.add_scalar(f"xp/{name}", value, global_step=self.last_step)
        image = _image(heatmap)
        if image is not None:
            self.writer.add_image("xp/heatmap", image, global_step=self.last_step, dataformats="HWC")
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


class WandbLogger:
    package, extra = "wandb", "wandb"
    about = "one W&B run per run directory, files in RUN_DIR/wandb/"

    @classmethod
    def preflight(cls) -> None:
        """Without credentials ``wandb.init`` fails at the first logged chunk, after training has begun: ask first
        (no prompt, no network), unless W&B is told to log locally."""
        wandb = require(cls.package, cls.extra, "--logger wandb")
        if os.environ.get("WANDB_MODE", "").lower() in ("offline", "disabled", "dryrun"):
            return
        if not wandb.login(prompt=False, verify=False):
            raise LoggerSetupError(
                "--logger wandb: no W&B API key; run `wandb login`, set WANDB_API_KEY, or set WANDB_MODE=offline "
                "to log into the run directory only"
            )

    def __init__(self, run_dir: Path, config: Config):
        self.wandb = require(self.package, self.extra, "--logger wandb")
        run_dir = Path(run_dir)
        self.run = self.wandb.init(
            project=os.environ.get("WANDB_PROJECT", "ocv2"),
            dir=str(run_dir),
            name=run_dir.name,
            id=_wandb_id(run_dir.name),
            resume="allow",
            config=config.to_dict(),
        )

    def log_rows(self, rows: Sequence[MetricsRow]) -> None:
        # W&B steps must grow: one log call per update, holding every seed's numbers.
        by_update: dict[int, dict] = defaultdict(dict)
        for row in rows:
            entry = by_update[row.update]
            entry["env_steps"] = row.env_steps
            entry.update({scalar_tag(name, row.seed): value for name, value in measurements(row).items()})
        for update in sorted(by_update):
            self.run.log(by_update[update], step=update)

    def log_xp(self, summary: Mapping, heatmap: Path | None) -> None:
        self.run.summary.update({f"xp/{k}": v for k, v in xp_scalars(summary).items()})
        if heatmap is not None and Path(heatmap).is_file():
            self.run.log({"xp/heatmap": self.wandb.Image(str(heatmap))})

    def close(self) -> None:
        self.run.finish()


def _wandb_id(name: str) -> str:
    """W&B run ids may not contain / \\ # ? % : and are at most 64 characters."""
    cleaned = "".join(c if c.isalnum() or c in "-_." else "-" for c in name)
    return cleaned[:64] or "ocv2-run"


#: Every logger by its ``--logger`` name; a new one is a class like those above (the three ``MetricsLogger``
#: methods; ``package`` and ``extra`` unless it imports nothing beyond the core, ``about`` for the help) and its entry
#: here: ``LOGGERS``, ``--logger``'s choices and help and the missing-package error follow (docs/extending.md).
_CLASSES = {"tensorboard": TensorBoardLogger, "wandb": WandbLogger}
LOGGERS = tuple(_CLASSES)


def logger_help() -> str:
    """``ocv2 train --logger``'s help, made from ``_CLASSES``: each logger's name, ``about`` and the extra it needs."""
    described = []
    for name, cls in _CLASSES.items():
        extra = getattr(cls, "extra", None) if getattr(cls, "package", None) else None
        notes = [note for note in (getattr(cls, "about", ""), extra and f"needs ocv2[{extra}]") if note]
        described.append(f"{name} ({'; '.join(notes)})" if notes else name)
    return "also log metrics, cross-play and heatmap to an experiment logger (repeatable): " + ", ".join(described)


def check_loggers(names: Iterable[str]) -> list[str]:
    """Validate logger names and that their packages are installed (before a run starts)."""
    names = list(dict.fromkeys(names))  # once each, in the order given
    for name in names:
        if name not in _CLASSES:
            raise ValueError(f"unknown logger {name!r}; choose from {', '.join(LOGGERS)}")
    for name in names:
        package = getattr(_CLASSES[name], "package", None)  # None: a logger that imports nothing beyond the core
        if package is not None:
            require(package, _CLASSES[name].extra, f"--logger {name}")
        preflight = getattr(_CLASSES[name], "preflight", None)
        if preflight is not None:
            preflight()
    return names


def make_loggers(names: Iterable[str], run_dir: Path, config: Config) -> list[MetricsLogger]:
    return [_CLASSES[name](run_dir, config) for name in check_loggers(names)]

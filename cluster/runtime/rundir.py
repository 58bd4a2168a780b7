"""The run directory every backend writes (issue 3/4 layout):

    RUN_DIR/config.yaml     resolved config (the run's identity: its fingerprint guards checkpoints)
            manifest.json   progress for --resume: status, updates done, snapshots, stage
            metrics.csv     one row per seed per update
            checkpoints/seed_<i>/update_<n>.msgpack
            xp/matrix.csv  xp/episodes.csv  xp/summary.json  xp/heatmap.png
            plots/training.png   gifs/*.gif
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from pathlib import Path

import numpy as np

from ocv2.atomic import atomic_write
from population.config import Config, ConfigError, dump_config, load_config

METRIC_FIELDS = ("seed", "update", "env_steps", "sparse_return", "shaped_return", "episodes", "loss", "actor_loss",
                 "value_loss", "entropy", "approx_kl", "clip_frac", "lr", "shaping_coef", "steps_per_s", "wall_s")


class RunDirError(ValueError):
    """A run directory that cannot be used as asked (exists, belongs to another config, ...)."""


class RunDir:
    def __init__(self, path):
        self.path = Path(path)

    # paths ------------------------------------------------------------------------------------------
    @property
    def config_path(self) -> Path:
        return self.path / "config.yaml"

    @property
    def manifest_path(self) -> Path:
        return self.path / "manifest.json"

    @property
    def metrics_path(self) -> Path:
        return self.path / "metrics.csv"

    def sub(self, *parts) -> Path:
        out = self.path.joinpath(*parts)
        out.parent.mkdir(parents=True, exist_ok=True)
        return out

    def subdir(self, *parts) -> Path:
        """A directory under the run directory, created if missing."""
        out = self.path.joinpath(*parts)
        out.mkdir(parents=True, exist_ok=True)
        return out

    # lifecycle --------------------------------------------------------------------------------------
    def create(self, config: Config, resume: bool = False) -> bool:
        """Prepare the directory for ``config``. Returns True when resuming an existing run.

        A new run needs a missing or empty directory; ``resume`` needs the same config fingerprint.
        """
        if self.config_path.exists():
            existing = self.load_config()
            if existing.fingerprint() != config.fingerprint():
                raise RunDirError(f"{self.path}: holds a run of a different config (fingerprint "
                                  f"{existing.fingerprint()} vs {config.fingerprint()}); choose another --out")
            if not resume:
                raise RunDirError(f"{self.path}: already holds a run; pass --resume to continue it or choose another --out")
            return True
        if self.path.exists() and any(self.path.iterdir()):
            raise RunDirError(f"{self.path}: exists and is not an ocv2 run directory (no config.yaml); choose another --out")
        if resume:
            raise RunDirError(f"{self.path}: nothing to resume (no config.yaml)")
        self.path.mkdir(parents=True, exist_ok=True)
        dump_config(config, self.config_path)
        self.write_manifest({"status": "created", "created": time.time()})
        return False

    def load_config(self) -> Config:
        try:
            return load_config(self.config_path)
        except ConfigError as error:
            raise RunDirError(f"{self.path}: its config.yaml is unusable: {error}") from None

    def read_manifest(self) -> dict:
        try:
            return json.loads(self.manifest_path.read_text())
        except FileNotFoundError:
            return {}

    def write_manifest(self, data: dict) -> None:
        atomic_write(self.manifest_path, json.dumps(data, indent=2, default=_json_default))

    def update_manifest(self, **changes) -> dict:
        data = self.read_manifest()
        data.update(changes)
        self.write_manifest(data)
        return data

    # metrics ----------------------------------------------------------------------------------------
    def append_metrics(self, rows: list[dict]) -> None:
        new = not self.metrics_path.exists()
        if new:
            fields = list(rows[0].keys()) if rows else list(METRIC_FIELDS)
        else:  # the file's own column order (rows restored from checkpoint meta come back key-sorted)
            with open(self.metrics_path, newline="") as handle:
                fields = next(csv.reader(handle), None) or list(rows[0].keys())
        with open(self.metrics_path, "a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=fields)
            if new:
                writer.writeheader()
            writer.writerows(rows)
            handle.flush()

    def truncate_metrics(self, after_update: int) -> None:
        """Drop rows past ``after_update`` (resume replays them from the checkpoint)."""
        rows = self.read_metrics()
        if not rows:
            return
        kept = [r for r in rows if int(float(r["update"])) <= after_update]
        header = list(rows[0].keys())
        write_csv(self.metrics_path, header, [[r[k] for k in header] for r in kept])

    def read_metrics(self) -> list[dict]:
        if not self.metrics_path.exists():
            return []
        with open(self.metrics_path, newline="") as handle:
            return list(csv.DictReader(handle))


def metric_rows(seeds, metrics, steps_per_s: float, wall_s: float, recipe_labels: list[str]) -> list[dict]:
    """Rows for ``metrics.csv`` from population metrics [S, n] (numpy)."""
    rows = []
    loss = metrics.loss
    for s, seed in enumerate(seeds):
        for u in range(np.shape(metrics.update)[1]):
            row = {
                "seed": seed, "update": int(metrics.update[s, u]), "env_steps": int(metrics.env_steps[s, u]),
                "sparse_return": _num(metrics.sparse_return[s, u]), "shaped_return": _num(metrics.shaped_return[s, u]),
                "episodes": int(metrics.episodes[s, u]), "loss": _num(loss.total[s, u]),
                "actor_loss": _num(loss.actor[s, u]), "value_loss": _num(loss.value[s, u]),
                "entropy": _num(loss.entropy[s, u]), "approx_kl": _num(loss.approx_kl[s, u]),
                "clip_frac": _num(loss.clip_frac[s, u]), "lr": _num(metrics.lr[s, u]),
                "shaping_coef": _num(metrics.shaping_coef[s, u]), "steps_per_s": round(steps_per_s, 1),
                "wall_s": round(wall_s, 2),
            }
            for r, label in enumerate(recipe_labels):
                row[f"return_recipe_{label}"] = _num(metrics.recipe_returns[s, u, r])
            rows.append(row)
    return rows


def _num(value) -> float | str:
    value = float(value)
    return "" if math.isnan(value) else round(value, 6)


def _json_default(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")


def write_csv(path: Path, header, rows) -> None:
    """A CSV file written atomically (a reader sees the old or the new file, never half of one)."""
    buffer = io.StringIO(newline="")
    writer = csv.writer(buffer)
    writer.writerow(header)
    writer.writerows(rows)
    atomic_write(path, buffer.getvalue())  # CSV rows keep their \r\n


def write_json(path: Path, data) -> None:
    atomic_write(path, json.dumps(data, indent=2, default=_json_default, allow_nan=True))

"""Population runs on Ray or in one process, the ``ocv2`` command line, the MCAP archive and browser play.

``cluster.train_population(config, run_dir, *, backend="ray"|"local", on_chunk=None, loggers=())`` is the
Python entry point (``cluster.api``); ``ocv2`` is ``cluster.cli.main``.
"""

import importlib

__all__ = ["train_population", "ChunkEvent", "MetricsRow"]


def __getattr__(name: str):
    # Resolved on first use: every ``ocv2`` command imports this package, and ``ocv2 layouts`` should not
    # pay for importing the trainer.
    if name in __all__:
        return getattr(importlib.import_module("cluster.api"), name)
    raise AttributeError(f"module 'cluster' has no attribute {name!r}")

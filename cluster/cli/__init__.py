"""The ``ocv2`` command line: argument parsing and one module per command group."""

from cluster.cli.main import main

__all__ = ["main"]

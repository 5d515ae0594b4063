"""Register a finished sweep's best cell's model in MLflow's model registry, to load as ``models:/<name>/<version>``.

``cdm-lab register EXPERIMENT --name NAME [--tracking-uri URI] [--run-id PARENT]``, also
``python sweeps/register.py EXPERIMENT --name NAME``: the command line of :mod:`sweeps.results.register`.
"""

import sys
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/register.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sweeps.results.register import build_parser, main

__all__ = ["build_parser", "main"]

if __name__ == "__main__":
    sys.exit(main())

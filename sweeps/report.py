"""Rebuild a finished sweep's comparison straight from MLflow: results table, the paper's layout, plots, panels.

``cdm-lab report EXPERIMENT [--tracking-uri URI] [--run-id PARENT] [--out DIR] [--log]``, also
``python sweeps/report.py EXPERIMENT``: the command line of :mod:`sweeps.results.publish`.
"""

import sys
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/report.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sweeps.results.publish import build_parser, main

__all__ = ["build_parser", "main"]

if __name__ == "__main__":
    sys.exit(main())

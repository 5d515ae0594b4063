"""Rebuild a finished sweep's comparison straight from MLflow: results table, the paper's layout, plots, panels.

``python sweeps/report.py EXPERIMENT [--tracking-uri URI] [--run-id PARENT] [--out DIR] [--log]``, also
``python sweeps/run.py --report EXPERIMENT``: the command line of :mod:`sweeps.results.publish`.
"""

import sys
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/report.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sweeps.results.publish import main

if __name__ == "__main__":
    sys.exit(main())

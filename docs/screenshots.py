"""The README's pictures of a finished sweep, taken from its MLflow store in headless Chromium.

``python docs/screenshots.py --tracking-uri sqlite:///…/mlflow.db [--experiment point_size] [--out docs]``

Starts ``mlflow server`` on the store (127.0.0.1, a free port), opens the sweep's saved view, the
comparison of its child runs, the parent run's page and the 3D viewer artifact in Debian's
``chromium``, and writes downscaled PNGs into ``--out``, together with the parent run's
``metric_vs_value.png`` and ``reconstructions.png``. ``tests/integration/test_compare.py`` drives the
same functions against its smoke sweep.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["chromium_page", "main", "mlflow_server", "pages", "shrink"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def mlflow_server(uri: str, log: Path) -> Iterator[str]:
    """``mlflow server`` on ``uri`` bound to 127.0.0.1; yields its address; stops its process group on exit."""
    port = _free_port()
    # No background job runner (a pool of worker processes) and one web worker: the UI needs neither.
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    with log.open("w") as out:
        command = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", uri, "--host", "127.0.0.1",
                   "--port", str(port), "--workers", "1"]
        server = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        url = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 90
            while True:
                try:
                    urllib.request.urlopen(f"{url}/health", timeout=2)
                    break
                except OSError:
                    if server.poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError(f"mlflow server did not come up: {log.read_text()[-3000:]}") from None
                    time.sleep(0.5)
            yield url
        finally:
            os.killpg(server.pid, signal.SIGTERM)
            try:
                server.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(server.pid, signal.SIGKILL)
                server.wait()


def chromium_page(chromium: str, url: str, screenshot: Path, profile: Path, width: int = 1600, height: int = 800) -> str:
    """The DOM of ``url`` once the page has rendered (15 s of virtual time), and a screenshot of it."""
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars",
           f"--user-data-dir={profile}", "--virtual-time-budget=15000", f"--window-size={width},{height}",
           f"--screenshot={screenshot}", "--dump-dom", url]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=profile, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"chromium failed on {url}: {done.stderr[-2000:]}")
    return done.stdout


def pages(server: str, experiment_id: str, parent_run_id: str, child_run_ids: list[str]) -> dict[str, str]:
    """Screenshot name → URL on ``server``: the sweep's view, its children compared, the parent run."""
    ids = json.dumps(child_run_ids, separators=(",", ":"))
    return {
        "mlflow_sweep_view.png": f"{server}/#/experiments/{experiment_id}/runs?viewStateShareKey=sweep-{parent_run_id}",
        "mlflow_compare.png": (f"{server}/#/compare-runs?runs={urllib.parse.quote(ids)}"
                               f"&experiments={urllib.parse.quote(json.dumps([experiment_id]))}"),
        "mlflow_parent_run.png": f"{server}/#/experiments/{experiment_id}/runs/{parent_run_id}",
    }


def shrink(source: Path, target: Path, width: int = 1000) -> Path:
    """A ``width``-pixel, 64-colour copy (small enough to commit)."""
    from PIL import Image

    img = Image.open(source).convert("RGB")
    img = img.resize((width, round(img.height * width / img.width)), Image.LANCZOS)
    target.parent.mkdir(parents=True, exist_ok=True)
    img.quantize(colors=64).save(target, optimize=True)
    return target


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="docs/screenshots.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--tracking-uri", required=True, help="the sweep's MLflow store, e.g. sqlite:////abs/mlflow.db")
    p.add_argument("--experiment", default="point_size", help="the sweep's experiment (= its spec's name)")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parent, help="folder for the PNGs (default: docs/)")
    args = p.parse_args(argv)
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    from mlflow import MlflowClient

    chromium = shutil.which("chromium")
    if chromium is None:
        print("error: Debian's chromium is not installed (apt-get install chromium)", file=sys.stderr)
        return 2
    client = MlflowClient(args.tracking_uri)
    exp = client.get_experiment_by_name(args.experiment)
    parents = [] if exp is None else client.search_runs([exp.experiment_id], "tags.kind = 'sweep'",
                                                        order_by=["attributes.start_time DESC"], max_results=1)
    if not parents:
        print(f"error: --experiment {args.experiment}: no sweep in {args.tracking_uri}", file=sys.stderr)
        return 2
    parent = parents[0].info.run_id
    children = [r.info.run_id for r in client.search_runs([exp.experiment_id], f"tags.mlflow.parentRunId = '{parent}'")
                if "rerun_of" not in r.data.tags]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        with mlflow_server(args.tracking_uri, tmp / "server.log") as server:
            for name, url in pages(server, exp.experiment_id, parent, children).items():
                chromium_page(chromium, url, tmp / name, tmp)
                print(shrink(tmp / name, args.out / name))
        for artifact, name in (("reconstructions/reconstructions.html", None), ("plots/metric_vs_value.png", "metric_vs_value.png"),
                               ("reconstructions/reconstructions.png", "reconstructions.png")):
            local = Path(client.download_artifacts(parent, artifact, str(tmp)))
            if name is None:
                chromium_page(chromium, local.as_uri(), tmp / "viewer.png", tmp, 1600, 700)
                print(shrink(tmp / "viewer.png", args.out / "reconstructions_viewer.png"))
            else:
                print(shrink(local, args.out / name, 1200))
    return 0


if __name__ == "__main__":
    sys.exit(main())

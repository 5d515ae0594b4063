"""Take the README's pictures of a finished sweep from its MLflow store, in headless Chromium.

``python docs/screenshots.py --tracking-uri sqlite:///…/mlflow.db [--experiment point_size] [--out docs]``

Starts ``mlflow server`` on the store (127.0.0.1, a free port), opens the sweep's saved view, the comparison of
its child runs, the parent run's page and its first child run's page (the first screen at 1,280 × 800 in a fresh
profile: MLflow's default panels, its Assistant open) and the 3D viewer artifact in Debian's ``chromium``, and
writes downscaled PNGs into ``--out``, together with the parent run's ``metric_vs_value.png`` and
``reconstructions.png``: every picture in ``docs/``. ``tests/integration/test_compare.py`` drives the same
functions against its smoke sweep.
"""

from __future__ import annotations

import argparse
import base64
import fcntl
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "GENAI_ENTRIES",
    "PAGE_TEXT",
    "chromium_page",
    "first_screen",
    "free_port",
    "main",
    "mlflow_server",
    "pages",
    "shrink",
    "wait_http",
]


STARTUP_S = 240.0
"""How long a local server may take to answer: minutes on a loaded 2-core machine (benchmarks/RESULTS.md)."""


def free_port() -> int:
    """A TCP port free on every interface (Ray's GCS and raylet listen on all of them)."""
    with socket.socket() as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def wait_http(url: str, proc: subprocess.Popen, log: Path, headers: dict[str, str] | None = None,
              timeout_s: float = STARTUP_S) -> None:
    """Poll ``url`` until it answers 200.

    Raises:
        RuntimeError: the server process ``proc`` exited, or ``timeout_s`` passed; with the tail of its ``log``.
    """
    t0 = time.monotonic()
    last = "no answer yet"
    while time.monotonic() - t0 < timeout_s:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
        try:
            # A long read timeout: a slow first answer abandoned would only queue the next request behind it.
            with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=30) as resp:
                if resp.status == 200:
                    return
                last = f"HTTP {resp.status}"
        except urllib.error.HTTPError as exc:
            last = f"HTTP {exc.code}"
        except (urllib.error.URLError, ConnectionError, TimeoutError) as exc:
            last = repr(exc)  # not listening yet, or busy starting
        time.sleep(0.5)
    raise RuntimeError(
        f"{url} did not answer within {timeout_s:.0f} s (last: {last}); server log:\n{log.read_text()[-3000:]}"
    )


@contextmanager
def mlflow_server(uri: str, log: Path, artifacts: Path | None = None, grace_s: float = 15.0) -> Iterator[str]:
    """``mlflow server`` on ``uri`` bound to 127.0.0.1; yields its address; stops its process group on exit.

    ``artifacts``: where the server keeps the artifacts clients upload through it (``mlflow-artifacts:/``),
    as ``cluster/README.md`` starts it; None serves the store's own. ``grace_s``: how long it may take to
    stop before it is killed (uvicorn waits on idle keep-alive connections).
    """
    port = free_port()
    # No background job runner (a pool of worker processes) and one web worker: the UI needs neither.
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    command = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", uri, "--host", "127.0.0.1",
               "--port", str(port), "--workers", "1"]
    if artifacts is not None:
        command += ["--artifacts-destination", str(artifacts)]
    with log.open("w") as out:
        server = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_http(f"{url}/health", server, log)
        yield url
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()


def chromium_page(
    chromium: str, url: str, screenshot: Path, profile: Path, width: int = 1600, height: int = 800
) -> str:
    """The DOM of ``url`` once the page has rendered (15 s of virtual time), and a screenshot of it."""
    profile.mkdir(parents=True, exist_ok=True)
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars",
           f"--user-data-dir={profile}", "--virtual-time-budget=15000", f"--window-size={width},{height}",
           f"--screenshot={screenshot}", "--dump-dom", url]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=profile, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"chromium failed on {url}: {done.stderr[-2000:]}")
    return done.stdout


def _above(fd: int, low: int) -> int:
    """``fd`` moved to the lowest free descriptor ≥ ``low``."""
    moved = fcntl.fcntl(fd, fcntl.F_DUPFD, low)
    os.close(fd)
    return moved


class _Pipe:
    """Chromium's DevTools protocol over ``--remote-debugging-pipe`` (JSON messages ended by NUL on the
    child's file descriptors 3 and 4): no WebSocket client, no extra package."""

    def __init__(self, chromium: str, profile: Path, width: int, height: int):
        profile.mkdir(parents=True, exist_ok=True)
        to_child, self._to_child = os.pipe()
        self._from_child, from_child = os.pipe()
        # bash puts the pipes on the child's 3 (our commands) and 4 (its replies), then runs chromium. Both
        # are moved above 4 first, so neither redirection overwrites the other pipe's end (and bash, unlike
        # dash, reads descriptors past 9).
        to_child, from_child = (_above(fd, 10) for fd in (to_child, from_child))
        cmd = ["bash", "-c", f'exec "$0" "$@" 3<&{to_child} 4>&{from_child}', chromium, "--headless", "--no-sandbox",
               "--disable-gpu", "--no-first-run", "--disable-background-networking", "--disable-component-update",
               "--disable-sync", "--hide-scrollbars", "--remote-debugging-pipe",
               f"--user-data-dir={profile}", f"--window-size={width},{height}", "about:blank"]
        self.process = subprocess.Popen(cmd, pass_fds=(to_child, from_child), cwd=profile,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(to_child)
        os.close(from_child)
        self._buffer, self._id = b"", 0

    def call(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 60) -> dict:
        """Send one command and return its ``result`` (events in between are skipped)."""
        self._id += 1
        message = {"id": self._id, "method": method, "params": params or {}} | (
            {"sessionId": session} if session else {}
        )
        os.write(self._to_child, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            while b"\0" not in self._buffer:
                ready, _, _ = select.select([self._from_child], [], [], max(0.0, deadline - time.monotonic()))
                chunk = os.read(self._from_child, 1 << 20) if ready else b""
                if not chunk:
                    raise RuntimeError(f"chromium gave no answer to {method} within {timeout} s")
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=10)
        except RuntimeError:
            self.process.kill()
        self.process.wait(timeout=30)
        os.close(self._to_child)
        os.close(self._from_child)


# Whether each text is drawn in the first screen: the centre of the element holding it lies in the window
# and inside every ancestor that clips its content (a description folded behind "Show more", a table
# scrolled sideways), and no ancestor hides it.
_PLACE = """(texts => texts.map(text => {
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  for (let node = walker.nextNode(); node; node = walker.nextNode()) {
    if (!node.textContent.includes(text)) continue;
    const box = node.parentElement.getBoundingClientRect(), x = box.left + box.width / 2, y = box.top + box.height / 2;
    if (!(box.width > 0 && x >= 0 && x < innerWidth && y >= 0 && y < innerHeight)) return false;
    for (let a = node.parentElement; a; a = a.parentElement) {
      const style = getComputedStyle(a);
      if (style.visibility === "hidden" || style.display === "none" || style.opacity === "0") return false;
      if (style.overflowX !== "visible" || style.overflowY !== "visible") {
        const clip = a.getBoundingClientRect();
        if (x < clip.left || x > clip.right || y < clip.top || y > clip.bottom) return false;
      }
    }
    return true;
  }
  return false;
}))"""


def first_screen(chromium: str, url: str, texts: list[str], screenshot: Path, profile: Path, width: int = 1280,
                 height: int = 800, timeout: float = 90, wait_for: list[str] | None = None) -> dict[str, bool]:
    """Whether each of ``texts`` is visible in the first screen (``width`` × ``height``, no scrolling) of
    ``url``, once every one of them (or of ``wait_for``: texts that must be absent are not waited for) is
    in the page (or ``timeout`` seconds have passed); also a
    screenshot of that screen. ``profile``: the browser's profile folder (a new one is a first visit)."""
    browser = _Pipe(chromium, profile, width, height)
    try:
        target = browser.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = browser.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        browser.call("Emulation.setDeviceMetricsOverride", {"width": width, "height": height, "deviceScaleFactor": 1,
                                                            "mobile": False}, session)
        browser.call("Page.navigate", {"url": url}, session)
        probe = (
            f"{json.dumps(texts if wait_for is None else wait_for)}"
            ".every(t => document.body && document.body.innerText.includes(t))"
        )
        deadline = time.monotonic() + timeout
        while not browser.call("Runtime.evaluate", {"expression": probe, "returnByValue": True}, session)["result"].get(
            "value"
        ):
            if time.monotonic() > deadline:
                break
            time.sleep(1)
        time.sleep(2)  # let the last layout pass settle (fonts, the table's column widths)
        found = browser.call(
            "Runtime.evaluate", {"expression": f"{_PLACE}({json.dumps(texts)})", "returnByValue": True}, session
        )
        shot = browser.call("Page.captureScreenshot", {"format": "png"}, session)
        screenshot.write_bytes(base64.b64decode(shot["data"]))
        return dict(zip(texts, found["result"]["value"]))
    finally:
        browser.close()


def pages(server: str, experiment_id: str, parent_run_id: str, child_run_ids: list[str]) -> dict[str, str]:
    """Screenshot name → URL on ``server``, each opening MLflow's model-training workflow (the runner's
    links do): the sweep's view, its children compared, the parent run, the first child run."""
    from sweeps.store.tracking import ui_link

    ids = json.dumps(child_run_ids, separators=(",", ":"))
    return {
        "mlflow_sweep_view.png": f"{server}/"
        f"{ui_link(f'#/experiments/{experiment_id}/runs?viewStateShareKey=sweep-{parent_run_id}')}",
        "mlflow_compare.png": f"{server}/"
        + ui_link(
            f"#/compare-runs?runs={urllib.parse.quote(ids)}"
            f"&experiments={urllib.parse.quote(json.dumps([experiment_id]))}"
        ),
        "mlflow_parent_run.png": f"{server}/{ui_link(f'#/experiments/{experiment_id}/runs/{parent_run_id}')}",
        "mlflow_child_run.png": f"{server}/{ui_link(f'#/experiments/{experiment_id}/runs/{child_run_ids[0]}')}",
    }


GENAI_ENTRIES = ("Sessions", "Judges", "Evaluation runs", "Prompts", "AI Gateway", "Agent versions")
"""Entries of MLflow 3's GenAI navigation that its model-training navigation (Runs, Models, Traces) lacks."""

PAGE_TEXT = {
    "mlflow_sweep_view.png": "vs reference",
    "mlflow_compare.png": "Comparing",
    "mlflow_parent_run.png": "About this run",
    "mlflow_child_run.png": "About this run",
}
"""The text each page of :func:`pages` shows once it has rendered its data; every page is shot as its
first screen at 1,280 × 800 (:func:`first_screen`) in a fresh profile, MLflow's default panels open
(the Assistant too): what a reader sees unscrolled on a first visit."""


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
    p.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parent, help="folder for the PNGs (default: docs/)"
    )
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
    children = [r.info.run_id for r in client.search_runs([exp.experiment_id], f"tags.mlflow.parentRunId = '{parent}'",
                                                          order_by=["attributes.start_time ASC"])
                if "rerun_of" not in r.data.tags]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        with mlflow_server(args.tracking_uri, tmp / "server.log") as server:
            for name, url in pages(server, exp.experiment_id, parent, children).items():
                # Each page's first screen once the text a reader looks for is in it, in a fresh profile.
                first_screen(chromium, url, [PAGE_TEXT[name]], tmp / name, Path(tempfile.mkdtemp(dir=tmp)))
                print(shrink(tmp / name, args.out / name))
        for artifact, name in (
            ("reconstructions/reconstructions.html", None),
            ("plots/metric_vs_value.png", "metric_vs_value.png"),
            ("reconstructions/reconstructions.png", "reconstructions.png"),
        ):
            local = Path(client.download_artifacts(parent, artifact, str(tmp)))
            if name is None:
                chromium_page(chromium, local.as_uri(), tmp / "viewer.png", tmp, 1600, 700)
                print(shrink(tmp / "viewer.png", args.out / "reconstructions_viewer.png"))
            else:
                print(shrink(local, args.out / name, 1200))
    return 0


if __name__ == "__main__":
    sys.exit(main())

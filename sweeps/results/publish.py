"""Rebuild a finished sweep's comparison straight from MLflow: results table, the paper's layout, plots, panels.

``cdm-lab report EXPERIMENT [--tracking-uri URI] [--run-id PARENT] [--out DIR] [--log]`` writes ``results.{md,csv}``
and the plots into ``--out`` (default ``results/<experiment>/report``); ``--log`` also logs the plots onto the
parent run. A failed trial is a "failed" row, not a crash; an unknown experiment exits 2 listing the known ones.
The runner calls :func:`publish` at the end of every sweep. The sweep is read back by :mod:`sweeps.results.sweep`.
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import tempfile
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cdm.baseline_names import BASELINES
from cdm.cli import add_out, command_parser
from cdm.interrupt import interruptible
from cdm.metric_names import CD, F1, METRICS, rounded
from cdm.metric_names import label as metric_label
from sweeps.compare.gallery import grid_png, panel_input, viewer_html
from sweeps.compare.plots import PlotPoint, has_curve, metric_vs_value, optuna_plots, read_ply, training_curves
from sweeps.compare.rules import PROTOCOL_NOTE, baseline_key, headline
from sweeps.compare.table import ResultsTable
from sweeps.plan.search import optuna_distributions
from sweeps.plan.spec import Spec
from sweeps.plan.trials import split_label
from sweeps.results.sweep import SweepRecord, TrialRecord, open_sweep, results_table, trial_records
from sweeps.results.view import headline_name, row_tags, share_view
from sweeps.store.files import StoreError
from sweeps.store.read import ReportError, last_eval_files, last_objects, metric_histories
from sweeps.store.tracking import check_tracking_uri, resolve_tracking_uri, ui_link

__all__ = ["DESCRIPTION_WIDTH", "build_parser", "describe_sweep", "describe_trial", "main", "open_given", "panels",
           "publish", "reconstructions", "sweep_arguments", "write_plots"]


def _histories(
    record: SweepRecord, trials: list[TrialRecord], keys: tuple[str, ...]
) -> dict[str, dict[str, list[tuple[int, float]]]]:
    """Trial label → metric → ``(step, value)`` history, for the trials that logged any of ``keys``."""
    out = {}
    for t in trials:
        if t.run_id is not None:
            history = metric_histories(record.client, t.run_id, keys)
            if any(history.values()):
                out[t.outcome.label] = history
    return out


def write_plots(
    record: SweepRecord, trials: list[TrialRecord], folder: Path, table: ResultsTable | None = None
) -> list[Path]:
    """``metric_vs_value.png`` (with ``table``: each cell's paired interval against the reference),
    ``training_curves.png`` and, for Optuna sweeps, Optuna's history and importances."""
    spec, folder = record.spec, Path(folder)
    metric = spec.metric.name
    done = [t for t in trials if t.outcome.finished]
    points = [PlotPoint(t.outcome.cell, t.values, t.outcome.metrics, t.outcome.paper, t.outcome.paper_label)
              for t in done]
    diffs = {t.outcome.cell: table.difference(t.outcome.cell, metric) for t in done} if table else {}
    intervals = {cell: (d.low, d.high) for cell, d in diffs.items() if d is not None}
    paths = []
    if points:
        paths.append(metric_vs_value(points, metric, record.title, folder / "metric_vs_value.png",
                                     spec.paper.table if spec.paper else "paper", intervals,
                                     f1_thresholds=[t.outcome.f1_threshold for t in done]))
    histories = _histories(record, trials, ("train/loss", "train/loss_diffusion", metric))
    curves = {label: history for label, history in histories.items() if has_curve(history, metric)}
    if curves:
        cells = {t.outcome.label: t.outcome.cell for t in trials}
        thresholds = [t.outcome.f1_threshold for t in trials if t.outcome.label in curves]
        paths.append(training_curves(curves, cells, metric, record.title, folder / "training_curves.png",
                                     f1_thresholds=thresholds))
    if spec.search.sampled:
        searched = [(t.values, t.outcome.metrics if t.outcome.finished and metric in t.outcome.metrics else None)
                    for t in trials if set(t.values) == set(spec.search.space)]
        if searched:
            paths += optuna_plots(searched, optuna_distributions(spec.search.space), spec.metric.mode, metric, folder)
    return paths


def panels(record: SweepRecord, trials: list[TrialRecord], folder: Path, per_trial: int = 2) -> dict[str, list[Path]]:
    """Download up to ``per_trial`` PNG panels (and their PLY clouds) of each finished trial's last evaluation.

    Returns:
        Trial label → local PNG paths, the PLY of each beside it under the same stem.
    """
    out = {}
    for t in trials:
        if t.run_id is None or not t.outcome.finished:
            continue
        files = last_eval_files(record.client, t.run_id)
        pngs = sorted(f for f in files if f.endswith(".png"))[:per_trial]
        clouds = {Path(f).name: f for f in files if f.endswith(".ply")}  # panels/<stem>.png beside clouds/<stem>.ply
        dest = Path(folder) / t.run_id
        for f in pngs + [clouds[Path(p).stem + ".ply"] for p in pngs if Path(p).stem + ".ply" in clouds]:
            record.client.download_artifacts(t.run_id, f, str(dest))
        out[t.outcome.label] = [dest / Path(f).name for f in pngs]  # download_artifacts keeps only the file name
    return out


DESCRIPTION_WIDTH = 200
"""Most characters on one line of a run description. MLflow renders each line break (a collapsed
paragraph would hide the rest), so prose goes one sentence a line, wrapped only past this width."""


def _prose(text: str, bullet: bool = False) -> str:
    """``text`` one sentence a line (a list item when ``bullet``), no line over :data:`DESCRIPTION_WIDTH`."""
    lead, indent = ("- ", "  ") if bullet else ("", "")
    lines = []
    for sentence in re.split(r"(?<=[.;])\s+(?=[A-Z*(])", text.strip()):
        lines += textwrap.wrap(sentence, DESCRIPTION_WIDTH, initial_indent=lead if not lines else indent,
                               subsequent_indent=indent, break_long_words=False, break_on_hyphens=False)
    return "\n".join(lines)


def describe_sweep(
    spec: Spec, profile: str, profile_description: str, table: ResultsTable, card: Sequence[str] = ()
) -> str:
    """The parent run's description (Markdown, the run page's first block), the answer first: the
    best cell's verdict sentence, the narrow table (cell, metric, partner, Δ with its interval,
    verdict) that fits MLflow's description pane at 1,280 px — MLflow shows a description's first
    lines and folds the rest behind "Show more" — then the other verdict sentences, the notes, the
    protocol card's changes (``sweeps/plan/protocol.py``; their sources in ``results.md``) and what was
    swept with which profile. The wide table (paper's column, per category, baselines beaten) is the
    run's ``results.md``."""
    better = "lower" if spec.metric.mode == "min" else "higher"
    head, *rest = table.summary or [table.headline]
    out = [_prose(f"**{spec.name}**, profile **{profile}**, by {spec.metric.name} ({better} is better): {head}."),
           table.grid(table.answer or None),
           "\n".join(_prose(line, bullet=True) for line in rest),
           _prose("Every column (the paper's numbers, per category, the baselines each cell beats) is in this run's "
                  "`results.md` artifact.")]
    notes = [n for n in table.notes if not n.startswith(PROTOCOL_NOTE)]
    out += ["\n".join(_prose(n, bullet=True) for n in notes)] if notes else []
    # The card's changes without their sources (each line "deviation: <change> (<source>)"): results.md lists
    # them whole.
    out += ["**Protocol card** (sources in `results.md`):\n" + "\n".join(
        _prose(line.removeprefix("deviation: ").split(" (", 1)[0], bullet=True) for line in card)] if card else []
    out += [_prose(f"**{spec.name}**: {spec.description}".rstrip(": ")),
            _prose(f"Profile **{profile}**: {profile_description}".rstrip(": "))]
    return "\n\n".join(part for part in out if part)


def _best_baseline(record: SweepRecord, trials: list[TrialRecord]) -> str | None:
    """The baseline scoring best on the sweep's metric (F1 when the metric is neither CD nor F1)."""
    metric, mode = record.spec.metric.name, record.spec.metric.mode
    short = metric.removeprefix("eval/") if metric.removeprefix("eval/") in METRICS else F1.name
    mode = mode if short == metric.removeprefix("eval/") else "max"
    means = {}
    for b in BASELINES:
        key = baseline_key(b, short)
        if values := [t.outcome.metrics[key] for t in trials if key in t.outcome.metrics]:
            means[b] = statistics.fmean(values)
    return (min if mode == "min" else max)(means, key=means.__getitem__) if means else None


def reconstructions(record: SweepRecord, trials: list[TrialRecord], folder: Path) -> list[Path]:
    """``reconstructions.png`` (a grid) and ``reconstructions.html`` (a 3D viewer) of the drawn objects:
    rows the objects every cell drew at its last evaluation, columns each cell (its first finished
    seed), the ground truth and the best baseline. Empty when no finished trial drew an object."""
    firsts: dict[str, TrialRecord] = {}
    for t in trials:
        if t.run_id is not None and t.outcome.finished:
            firsts.setdefault(t.outcome.cell, t)
    # Evaluation folders differ by step: each cell's files by name, the same objects in every column.
    files = {cell: {Path(f).name: f for f in last_eval_files(record.client, t.run_id)} for cell, t in firsts.items()}
    first = next(iter(firsts), "")
    names = [n.removesuffix(".gt.ply") for n in files.get(first, {}) if n.endswith(".gt.ply")
             and all(n.removesuffix(".gt.ply") + ".ply" in found for found in files.values())]
    if not names:
        return []
    best = _best_baseline(record, trials)
    baseline = f"baseline: {best}" if best else None
    # The first column's object also gives the ground truth's and the best baseline's clouds.
    extra = {"ground truth": ".gt.ply"} | ({baseline: f".{best}.ply"} if baseline else {})
    gallery: dict[str, dict[str, np.ndarray]] = {}
    inputs = {}
    with tempfile.TemporaryDirectory() as tmp:
        def fetch(cell: str, name: str) -> Path:
            t = firsts[cell]
            return Path(record.client.download_artifacts(t.run_id, files[cell][name], str(Path(tmp) / t.run_id)))

        for cell in firsts:
            for name in names:
                wanted = {cell: f"{name}.ply"} | ({k: name + end for k, end in extra.items()} if cell == first else {})
                for label, file in wanted.items():
                    if file in files[cell]:
                        gallery.setdefault(name, {})[label] = read_ply(fetch(cell, file))
        for name in names:  # the input image, from the first cell's panel of that object
            if f"{name}.png" in files[first] and (found := panel_input(fetch(first, f"{name}.png"))) is not None:
                inputs[name] = found
    columns = [*firsts, "ground truth", *([baseline] if baseline else [])]
    title = f"{record.title}: reconstructions at the last evaluation"
    scores = _object_scores(record, firsts, best)
    thresholds = [t.outcome.f1_threshold for t in firsts.values()]
    return [grid_png(gallery, columns, title, folder / "reconstructions.png", scores, inputs, f1_thresholds=thresholds),
            viewer_html(gallery, columns, title, folder / "reconstructions.html", scores=scores)]


def _object_scores(
    record: SweepRecord, firsts: dict[str, TrialRecord], best: str | None
) -> dict[str, dict[str, tuple[float, float]]]:
    """Object file stem → column (each cell; the best baseline) → its ``(CD, F1)`` in ``objects.csv``."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for i, (cell, t) in enumerate(firsts.items()):
        for row in last_objects(record.client, t.run_id):
            stem = str(row["object_id"]).replace("/", "_")  # the clouds' file names (cdm/evaluate.py)
            scores = out.setdefault(stem, {})
            scores[cell] = (float(row[CD.name]), float(row[F1.name]))
            if i == 0 and best is not None and baseline_key(best, CD.name) in row:
                scores[f"baseline: {best}"] = (float(row[baseline_key(best, CD.name)]),
                                               float(row[baseline_key(best, F1.name)]))
    return out


def describe_trial(record: SweepRecord, trial: TrialRecord, table: ResultsTable) -> str:
    """A child run's description (Markdown, one paragraph): its cell and seed, its result, its cell
    against the reference cell and the baselines (from ``table``'s records), and a link to the sweep's
    parent run."""
    o, spec = trial.outcome, record.spec
    parent = f"[{record.title}]({ui_link(f'#/experiments/{record.experiment_id}/runs/{record.parent.info.run_id}')})"
    seed = split_label(o.label)[1] or "?"
    out = [f"**{o.cell}**, seed {seed}, a trial of the sweep {parent}."]
    if o.status == "failed":
        out.append(f"It failed: {o.error or 'no reason recorded'}.")
    elif not o.finished:
        out.append("It did not finish.")
    else:
        shown = [m for m in headline(spec.metric.name) if m in o.metrics]
        out.append("At its last evaluation "
                   + ", ".join(f"{metric_label(m, o.f1_threshold)} {rounded(o.metrics[m])}" for m in shown) + ".")
        cell, diff = table.record(o.cell), table.difference(o.cell, spec.metric.name)
        if o.cell == table.reference:
            out.append("Its cell is the reference cell the others are paired with.")
        elif diff is not None:
            out.append(f"Its cell against the reference cell: Δ{spec.metric.name.removeprefix('eval/')} {diff.text()} "
                       f"(95% paired interval), {cell['verdict']}.")
        if "beats baselines" in cell:
            beaten = str(cell["beats baselines"]).replace(";", ", ")
            out.append(f"Baselines it beats on {spec.metric.name}: {beaten or 'none'}.")
    return _prose(" ".join(out))


def publish(uri: str, parent_run_id: str, folder: Path) -> str:
    """End of a sweep: plots and reconstructions into ``folder`` and onto the parent run (``plots/``,
    ``reconstructions/``), a description and the view's columns (:func:`sweeps.results.view.row_tags`)
    on each child run, the headline as the parent's name, and the runs view; returns its path (``#/experiments/…``)."""
    record = open_sweep(uri, parent_run_id=parent_run_id)
    trials = trial_records(record)
    table = results_table(record, trials)
    for t in trials:
        if t.run_id is not None:
            tags = {"mlflow.note.content": describe_trial(record, t, table)} | row_tags(
                table, t.outcome.cell, record.spec.metric.name
            )
            # The fields the sweep set, in full: of ~84 params, the ones that vary (priors.point_size, not
            # model.raster_radius).
            tags |= {"swept": ", ".join(f"{k}={v}" for k, v in t.values.items())} if t.values else {}
            for key, value in tags.items():
                record.client.set_tag(t.run_id, key, value)
    record.client.update_run(parent_run_id, name=headline_name(record, table))
    for path in write_plots(record, trials, folder, table):
        record.client.log_artifact(parent_run_id, str(path), "plots")
    for path in reconstructions(record, trials, folder):
        record.client.log_artifact(parent_run_id, str(path), "reconstructions")
    return share_view(record, table)


def sweep_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``p`` with the arguments that name a finished sweep (``EXPERIMENT``, ``--tracking-uri``, ``--run-id``), as
    :func:`open_given` reads them."""
    p.add_argument("experiment", metavar="EXPERIMENT", help="MLflow experiment name (= the spec's name)")
    p.add_argument("--tracking-uri", default=None, metavar="URI",
                   help="MLflow URI (default: MLFLOW_TRACKING_URI, else sqlite:///<cwd>/mlflow.db)")
    p.add_argument("--run-id", default=None, metavar="RUN_ID",
                   help="parent run of the sweep (default: the experiment's latest sweep)")
    return p


def open_given(args: argparse.Namespace) -> SweepRecord:
    """The sweep :func:`sweep_arguments` named, its store checked first (a URI MLflow cannot open is one line, not
    its traceback).

    Raises:
        ReportError, StoreError: no such store or sweep; the message says which.
    """
    uri = resolve_tracking_uri(args.tracking_uri)
    check_tracking_uri(uri)
    return open_sweep(uri, args.experiment, args.run_id)


def build_parser() -> argparse.ArgumentParser:
    p = sweep_arguments(command_parser("report", __doc__.split("\n\n")[0], "point_size --out reports/point_size"))
    add_out(p, "results.{md,csv} and plots (default: results/<experiment>/report)", type=Path, default=None)
    p.add_argument("--log", action="store_true", help="also log the plots onto the parent run and save the UI view")
    return p


@interruptible("cdm-lab report")
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        record = open_given(args)
    except (ReportError, StoreError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = (args.out or Path("results") / record.experiment / "report").resolve()
    trials = trial_records(record)
    table = results_table(record, trials)
    md, csv = table.write(out)
    plots = write_plots(record, trials, out, table) + reconstructions(record, trials, out)
    print(table.text() + "\n")
    print(f"results: {md} and {csv}")
    print("plots: " + ", ".join(str(p) for p in plots))
    if args.log:
        for path in plots:
            record.client.log_artifact(record.parent.info.run_id, str(path), "plots")
        print(f"MLflow view of this sweep: <UI address>/{ui_link(share_view(record, table))}")
    return 0

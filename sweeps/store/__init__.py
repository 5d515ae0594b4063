"""The one store of a sweep's record: its folder (a local path or an object-store URI) and its MLflow runs.

Every byte it reads goes through :mod:`cdm.io` (an object store's through :func:`cdm.io.files.read_from`), every
file it writes through :mod:`cdm.io.write` or pyarrow, and every MLflow call through :func:`tracking.client`,
which waits on a busy SQLite store and keeps MLflow's artifact progress bars off the terminal. It imports no stage
of ``sweeps/``: what a record means (outcomes, tables, verdicts) is the stages' business.

The interface:

- write a trial's record: :class:`trial_run.TrialRun` (the trial's child run, fed by the trainer's callbacks);
- write the sweep's record: :class:`sweep_run.SweepRun` (the parent run: opened, children closed with Tune's
  verdict, baselines once per evaluation set);
- read a sweep's record: :func:`read.read_sweep` (parent, spec, plan, children) and the per-run readers of
  :mod:`.read` (:func:`read.trial_metrics`, :func:`read.last_objects`, :func:`read.metric_histories`, …);
- the MLflow store: :func:`tracking.resolve_tracking_uri`, :func:`tracking.check_tracking_uri`,
  :func:`tracking.client`;
- the sweep folder: :func:`files.sweep_location`, :func:`files.check_storage`, :func:`files.read_state`,
  :func:`files.read_record`/:func:`files.write_record`, :func:`files.publish_files`, :func:`files.write_file`,
  :func:`files.private_folder`, and :func:`files.check_resume_trust` before Tune unpickles its state.

A refusal is one line: :class:`files.StoreError` (a URI, folder or record that cannot be used) or
:class:`read.ReportError` (a sweep MLflow does not hold).
"""

"""Comparing cells, while the trials run and after: the results table, paired intervals (the one that
settles seeds among them), plots and the reconstructions gallery. Plain numbers, no Ray, no MLflow: the running
of the trials (each trial's outcome, seeds until settled) and the read-back of a finished sweep build on it.
"""

"""Comparing cells, while the trials run and after: the results table, paired intervals, the seeds-until-settled
rule, plots and the reconstructions gallery. Plain numbers, no Ray, no MLflow: the running of the trials (each
trial's outcome, the seed searcher's rule) and the read-back of a finished sweep build on it.
"""

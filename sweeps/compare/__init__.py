"""Stage 2, comparing cells (no Ray, no MLflow): the results table, paired intervals, the seeds-until-settled
rule, plots and the reconstructions gallery. Used while a sweep runs and after it.
"""

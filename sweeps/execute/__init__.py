"""Running the trials, the stage after planning: the Ray cluster, work shared by every cell, the Tune trainable
and its Train loop, seeds until settled (its rule and searcher), MLflow tracking, core leases, checkpoints and
the progress line.
"""

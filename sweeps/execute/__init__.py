"""Running the trials, the stage after planning: the Ray cluster, work shared by every cell, the Tune trainable
and its Train loop, the seed searcher, MLflow tracking, core leases, checkpoints and the progress line.
"""

"""Stage 4, a finished sweep read back from MLflow: its records, what it publishes (plots, descriptions, the
runs view) and the re-run of one trial.
"""

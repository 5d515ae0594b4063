"""A finished sweep read back from MLflow, the last stage: its records, what it publishes (plots, descriptions, the
runs view) and the re-run of one trial.
"""

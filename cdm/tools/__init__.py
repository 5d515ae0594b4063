"""Offline helpers that write the external inputs of :mod:`cdm.inputs` (run once, on the user's side)."""

__all__: list[str] = []

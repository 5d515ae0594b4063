"""Offline helpers that write the external inputs of :mod:`cdm.external_inputs` (run once, on the user's side)."""

__all__: list[str] = []

"""Data sets: the common sample format and a registry of data-set kinds."""

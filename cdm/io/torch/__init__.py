"""Torch files read as tensors and plain data, never by torch's own loader (:mod:`cdm.io.torch.load`)."""

from cdm.io.torch.load import (
                            CONFIG_CALLS,
                            MAX_NESTING,
                            MAX_PICKLE_OPS,
                            Pickled,
                            load_inert,
                            load_tensors,
                            pickle_bytes,
)

__all__ = ["CONFIG_CALLS", "MAX_NESTING", "MAX_PICKLE_OPS", "Pickled", "load_inert", "load_tensors",
           "pickle_bytes"]

"""Every file a user, a data set or a neighbour can write is read here, and every file a command writes
where a user points it is written here (docs/security.md, "Every outside byte through cdm/io/").

One module per kind: :mod:`~cdm.io.files` (regular files, bounded reads, gzip), :mod:`~cdm.io.json`,
:mod:`~cdm.io.yaml`, :mod:`~cdm.io.arrays` (``.npy``, ``.npz``), :mod:`~cdm.io.images`,
:mod:`~cdm.io.meshes`, :mod:`~cdm.io.csv`, :mod:`~cdm.io.safetensors` (the project's own weights, caches
and shards), :mod:`~cdm.io.torch` (foreign torch files: archive, inert unpickler),
:mod:`~cdm.io.names` (names and paths a file gives) and :mod:`~cdm.io.write` (the one no-follow atomic
writer). Nothing is imported here, so a reader of JSON does not pay for torch or OpenCV.
"""

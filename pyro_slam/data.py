"""The traversal data set (:class:`Traversal`): what simulators and log readers produce and
every inference routine consumes, with its ``.npz`` format, validation and atomic writes. It is
defined in the data layer :mod:`slamdata.traversal` that the simulators share; this module is
the library's name for it."""

from slamdata.traversal import (
    FORMAT_VERSION,
    DatasetError,
    Traversal,
    atomic_write,
    atomic_write_all,
    load,
    load_tensors,
    one_line,
    validate,
)

__all__ = [
    "FORMAT_VERSION",
    "DatasetError",
    "Traversal",
    "atomic_write",
    "atomic_write_all",
    "load",
    "load_tensors",
    "one_line",
    "validate",
]

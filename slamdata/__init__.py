"""The data layer that the simulators and the library share: the traversal data set
(:mod:`slamdata.traversal`: :class:`Traversal`, its ``.npz`` format, validation and atomic
writes) and angle wrapping (:mod:`slamdata.angles`). It imports neither ``simulators`` nor
``pyro_slam``, so the simulators produce what the library reads without importing it."""

from .angles import wrap_angle
from .traversal import (
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
    "DatasetError",
    "Traversal",
    "atomic_write",
    "atomic_write_all",
    "load",
    "load_tensors",
    "one_line",
    "validate",
    "wrap_angle",
]

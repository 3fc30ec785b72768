"""Register your own clouds: :func:`register` (Python) and ``lcreg register`` (command line).

Sits above the models and baselines (it builds them) and below the command line. Modules: :mod:`.inputs`
(paths, numpy, torch, Open3D → validated clouds), :mod:`.voxel` (automatic voxel size), :mod:`.methods` (methods
by short name and their steps), :mod:`.api` (:func:`register`, :class:`Registration`), :mod:`.outputs` (files
written), :mod:`.many` (``--pairs``: many pairs, scores), :mod:`.command` (``lcreg register``).
"""

from lcreg.registration.api import DEFAULT_METHOD, LowFitnessWarning, Registration, register
from lcreg.registration.methods import MethodError, available_methods

__all__ = ["DEFAULT_METHOD", "LowFitnessWarning", "MethodError", "Registration", "available_methods", "register"]

"""HandFE: muscle-driven finite-element grasp simulation of the human hand on FEniCSx.

Units throughout: mm, N, MPa (= N/mm^2), s. Names that cross an interface carry their unit
(``force_N``, ``area_mm2``).
"""

import os as _os

# Under mpirun every rank is a process on its own core: OpenBLAS's own threads (Debian's
# openblas-pthread) would oversubscribe the cores and slow MUMPS down. Must be set before numpy
# loads OpenBLAS; an explicit setting wins.
if int(_os.environ.get("OMPI_COMM_WORLD_SIZE", _os.environ.get("PMI_SIZE", "1"))) > 1:
    _os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    _os.environ.setdefault("OMP_NUM_THREADS", "1")

from handfe.errors import ConfigError, HandFEError, InputError, SolverError

__version__ = "0.1.0"
__all__ = ["ConfigError", "HandFEError", "InputError", "SolverError", "__version__"]

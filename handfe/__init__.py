"""HandFE: muscle-driven finite-element grasp simulation of the human hand on FEniCSx.

Units throughout: mm, N, MPa (= N/mm^2), s. Names that cross an interface carry their unit
(``force_N``, ``area_mm2``).
"""

from handfe.errors import ConfigError, HandFEError, InputError, SolverError

__version__ = "0.1.0"
__all__ = ["ConfigError", "HandFEError", "InputError", "SolverError", "__version__"]

"""Sensitivity studies (brief §1, issue 7): tissue laws and muscle forces perturbed one at a time
by +-5..20 %, run concurrently over MPI groups, resumable, tables as CSV and tornado charts.

Public API::

    from handfe.sensitivity import load_study, run_study, build_tables, refit_scaled
    study = load_study("sensitivity/cylindrical.toml")        # ConfigError on bad files
    run = run_study(study.with_mesh("coarse"), "results/sensitivity/cylindrical",
                    ranks_per_case=1, force=False)            # collective on COMM_WORLD
    r = refit_scaled(Ogden.skin(), 0.10, tissue="skin")       # N = 3 Ogden refit of P x 1.1

Modules: :mod:`.study` (TOML -> frozen dataclasses), :mod:`.refit` (material perturbation),
:mod:`.driver` (cases, MPI groups, case files, resume), :mod:`.tables` (CSV/PNG from disk).
"""

from handfe.sensitivity.driver import (
    RUNNERS,
    Case,
    StudyRun,
    case_id,
    execute_case,
    read_case,
    run_study,
    study_cases,
)
from handfe.sensitivity.refit import Refit, refit_scaled, uniaxial_nominal_stress
from handfe.sensitivity.study import Study, load_study, study_from_dict
from handfe.sensitivity.tables import build_tables

__all__ = ["RUNNERS", "Case", "Refit", "Study", "StudyRun", "build_tables", "case_id",
           "execute_case", "load_study", "read_case", "refit_scaled", "run_study",
           "study_cases", "study_from_dict", "uniaxial_nominal_stress"]

"""Calibration of the fingertip pulp to the 15-degree plate-compression deflections (brief §3:
2.8 mm at 2 N, 3.1 mm at 4 N; ``reference/fingertip_compression_15deg.csv``). Only these data
are used; other angles and the contact-patch sizes are predictions.

Law: the Mooney-Rivlin-type W = C01 (Ib2 - 3) + C20 (Ib1 - 3)^2 + (1/D1)(J - 1)^2, the family
of the brief's published fit, near-incompressible: nu = CALIBRATION_NU = 0.49999, i.e.
kappa = 2/D1 = 50 000 mu0 ~ 860 C20 (~2.2 MPa for the fitted set). The brief's nu = 0.49 ties
kappa to the tiny initial shear modulus (12 kPa for the first fit, below the 40-60 kPa
contact pressures): that compressible set loses volume instead of stiffening and is
Drucker-unstable in equibiaxial compression below stretch 0.67 and uniaxial below 0.565
(docs/materials.md). Stability in stretch is independent of the overall scale s; at fixed
C20/C01 = 117: nu = 0.4999 is stable in uniaxial and shear down to 0.3 but not in
equibiaxial compression below 0.52 (where J = 0.36); nu = 0.49999 is stable in uniaxial and
shear down to 0.3, equibiaxial down to 0.41, and keeps J >= 0.9 up to equibiaxial 0.6 (~500
kPa for the fitted scale, ~10x the scene's peak pressure); the incompressible limit is stable
throughout 0.3-3.

Why this law: finger-pad pulp is soft at small load and nearly rigid under moderate compression
(brief §3: 0.3 mm more travel from 2 N to 4 N). The C20 term gives that strain stiffening with
an initial shear modulus mu0 = 2 C01 > 0 and all coefficients >= 0, so the law is stable
(docs/materials.md) — unlike free Ogden exponents, which can fit two points with unphysical,
Drucker-unstable sets.

Two free parameters, fitted in two nested 1-D problems:
* scale s (C01 and C20 multiplied by s): every traction in the scene scales with s (stress at
  fixed nu, penalty k ~ E, Coulomb mu p, stick spring k_t = k_n), so the plate force at a given
  deflection is s F_1(d); the nail (E = 170 MPa, ~rigid) is the only part that does not scale.
  One displacement sweep F_1(d) thus gives d(F) for every s without another solve.
* stiffening ratio r = C20 / C01: one sweep per trial r, bounded scalar minimisation in log r.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from handfe.errors import InputError
from handfe.materials import MooneyRivlin
from handfe.paths import REFERENCE_DIR

BASE_C01_MPa = 0.00059
CALIBRATION_NU = 0.49999


def targets_15deg(path: Path = REFERENCE_DIR / "fingertip_compression_15deg.csv"):
    """[(force_N, deflection_mm, sd_mm)] of the 15-degree tests."""
    with Path(path).open() as fh:
        rows = list(csv.DictReader(fh))
    return [(float(r["load_N"]), float(r["deflection_mean_mm"]), float(r["deflection_std_mm"]))
            for r in rows if float(r["plate_angle_deg"]) == 15.0]


def sweep(ratio: float, *, mesh: str = "reduced", h_mm: float | None = None,
          d_points=(1.5, 2.0, 2.4, 2.8, 3.1, 3.4, 3.7, 4.0), comm=None,
          progress: Callable[[str], None] | None = None,
          nu: float = CALIBRATION_NU) -> tuple[np.ndarray, np.ndarray]:
    """Plate force (N) at the deflections ``d_points`` (mm), 15 degrees, material
    C01 = BASE_C01_MPa, C20 = ratio * C01, Poisson's ratio ``nu`` (each point fully converged,
    penetration <= 0.01)."""
    from handfe.fingertip_scene import FingertipCompression, FingertipConfig

    mat = MooneyRivlin(C10_MPa=0.0, C01_MPa=BASE_C01_MPa, C20_MPa=ratio * BASE_C01_MPa, nu=nu)
    sc = FingertipCompression(FingertipConfig(angle_deg=15.0, mesh=mesh, h_mm=h_mm,
                                              material=mat), comm=comm)
    F = []
    for d in d_points:
        sc._segment(float(d), initial=1.0)
        F.append(sc.plate_force())
        if progress:
            progress(f"    r = {ratio:.4g}: d = {d:.2f} mm -> F = {F[-1]:.4f} N")
    return np.asarray(d_points, dtype=float), np.asarray(F)


def deflection_at(force_N: float, d: np.ndarray, F: np.ndarray, scale: float) -> float:
    """Deflection where scale * F(d) = force_N (monotone cubic interpolation in log F)."""
    from scipy.interpolate import PchipInterpolator

    Fs = scale * F
    if not (Fs[0] <= force_N <= Fs[-1]):
        return math.nan
    return float(PchipInterpolator(np.log(Fs), d)(math.log(force_N)))


@dataclass
class CalibrationResult:
    C01_MPa: float
    C20_MPa: float
    nu: float
    ratio: float
    scale: float
    predicted_mm: list[float]
    measured_mm: list[float]
    residual_mm: float
    sweeps: int
    wall_s: float
    mesh: str


def best_scale(d: np.ndarray, F: np.ndarray, targets) -> tuple[float, float]:
    """(scale, rms deflection error mm) for one sweep, by bounded scalar minimisation."""
    from scipy.optimize import minimize_scalar

    def err(log_s: float) -> float:
        s = math.exp(log_s)
        e = [deflection_at(f, d, F, s) - dm for f, dm, _ in targets]
        return float(np.sqrt(np.mean(np.square(e)))) if all(np.isfinite(e)) else 10.0

    lo = math.log(max(t[0] for t in targets) / F[-1])   # largest force reached at d_max
    hi = math.log(min(t[0] for t in targets) / F[0])    # smallest force reached at d_min
    if lo >= hi:
        return math.nan, math.inf
    r = minimize_scalar(err, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6})
    return math.exp(r.x), float(r.fun)


def calibrate(*, mesh: str = "reduced", h_mm: float | None = None,
              ratio_bounds: tuple[float, float] = (0.5, 200.0), max_sweeps: int = 10,
              comm=None, progress: Callable[[str], None] | None = None,
              nu: float = CALIBRATION_NU, ratio: float | None = None) -> CalibrationResult:
    """Fit C01, C20 (Poisson's ratio ``nu`` fixed) to the 15-degree deflections at 2 N and 4 N.
    ``ratio`` given: C20/C01 is held at that value and only the scale is fitted (one sweep)."""
    from scipy.optimize import minimize_scalar

    if not 0 < ratio_bounds[0] < ratio_bounds[1]:
        raise InputError(f"ratio bounds {ratio_bounds}: need 0 < lo < hi")
    if ratio is not None and not (math.isfinite(ratio) and ratio > 0):
        raise InputError(f"ratio C20/C01 = {ratio!r} must be positive")
    if not 0.0 < nu < 0.5:
        raise InputError(f"nu = {nu!r} must be within (0, 0.5)")
    targets = targets_15deg()
    t0 = time.perf_counter()
    cache: dict[float, tuple[float, float, np.ndarray, np.ndarray]] = {}

    def objective(log_r: float) -> float:
        r = math.exp(log_r)
        d, F = sweep(r, mesh=mesh, h_mm=h_mm, comm=comm, progress=progress, nu=nu)
        s, e = best_scale(d, F, targets)
        cache[log_r] = (s, e, d, F)
        if progress:
            progress(f"  C20/C01 = {r:.4g}: best scale {s:.4g}, rms deflection error "
                     f"{e:.4f} mm")
        return e

    if ratio is not None:
        objective(math.log(ratio))
    else:
        minimize_scalar(objective, bounds=tuple(math.log(x) for x in ratio_bounds),
                        method="bounded", options={"maxiter": max_sweeps, "xatol": 0.02})
    log_r = min(cache, key=lambda k: cache[k][1])
    s, e, d, F = cache[log_r]
    r = math.exp(log_r)
    pred = [deflection_at(f, d, F, s) for f, _, _ in targets]
    return CalibrationResult(C01_MPa=s * BASE_C01_MPa, C20_MPa=s * r * BASE_C01_MPa, nu=nu,
                             ratio=r, scale=s, predicted_mm=pred,
                             measured_mm=[t[1] for t in targets], residual_mm=e,
                             sweeps=len(cache), wall_s=time.perf_counter() - t0,
                             mesh=mesh if h_mm is None else f"h={h_mm:g}")

"""Material perturbation as in the source study (brief §1): scale the nominal stress of the
tissue's uniaxial test curve by (1 + delta) at fixed strain and re-fit the N = 3 Ogden law.

Units: MPa for mu and stresses, stretches dimensionless. Tension positive.

* **Data.** The source's uniaxial test data are not published, only the fitted Ogden sets
  (reference/soft_tissue_ogden.json). The "baseline data" are therefore regenerated from the set:
  incompressible uniaxial nominal stress (the Abaqus fitting assumption)

      P(lambda) = sum_i 2 mu_i / alpha_i (lambda^(alpha_i - 1) - lambda^(-alpha_i/2 - 1))

  at ``n_points`` stretches evenly spaced over ``fit_stretch`` (default 0.6-1.5: the uniaxial
  *tension* range typical of skin/fat tests, up to 1.5, plus the *compression* range a grasp
  reaches in the pulp, down to 0.6), the point lambda = 1 (P = 0) left out.
* **Perturbation.** The target is (1 + delta) P(lambda) at the same stretches.
* **Refit.** ``scipy.optimize.least_squares`` (trust-region reflective, bounded) on the six
  parameters (mu_1..3, alpha_1..3), from several starts: the baseline set itself and
  deterministic perturbations of it (alphas x 0.8-1.2, mus x 0.7-1.3; fixed seed). Bounds:
  mu_i within +-10 max|mu_base| (MPa), alpha_i keeps the sign of the baseline alpha_i with
  0.5 <= |alpha_i| <= 20. Residuals are weighted
  r_k = (P_fit - P_target) / max(|P_target|, 0.05 max|P_target|): relative where the stress
  is not tiny, absolute (5 % of the curve's peak) near lambda = 1, so neither the large-stretch
  end nor the near-zero points dominate. The best start (smallest cost) wins.
* **Quality.** ``fit_rms_pct`` and ``fit_max_pct``: rms and max of |r_k| in %. A refit with
  ``fit_max_pct`` above the study's ``max_fit_error_pct`` (default 1 %) is *poor*.
* **Stability.** :func:`handfe.materials.drucker_stability` of the refit, incompressible, in
  uniaxial, equibiaxial and pure shear over ``stability_stretch`` (default 0.5-2.0, the range a
  grasp reaches). Incompressible because the fit is incompressible; the compressible loss of
  stability at nu = 0.49 under strong equibiaxial compression comes from the volumetric term and
  is shared by the baseline (docs/materials.md), so it is not a property of the refit.
* Note: scaling every mu_i by (1 + delta) reproduces the scaled curve exactly (P is linear in
  mu); the refit does not know that and lands near, not on, that set. ``mu_vs_scaled_pct``
  reports max_i |mu_i,fit - (1 + delta) mu_i,base| / max_i |(1 + delta) mu_i,base| in %, and
  ``alpha_change_pct`` the largest relative change of an alpha.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass

import numpy as np

from handfe.errors import InputError
from handfe.materials import Ogden, drucker_stability

N_TERMS = 3


def uniaxial_nominal_stress(mu, alpha, lam) -> np.ndarray:
    """Incompressible uniaxial nominal stress P11 (MPa) of an Abaqus-form Ogden law."""
    lam = np.asarray(lam, dtype=float)
    out = np.zeros_like(lam)
    for m, a in zip(mu, alpha, strict=True):
        out += 2.0 * m / a * (lam ** (a - 1.0) - lam ** (-0.5 * a - 1.0))
    return out


def stretch_grid(fit_stretch: tuple[float, float], n_points: int) -> np.ndarray:
    """``n_points`` stretches evenly over ``fit_stretch``, without lambda = 1 (P = 0 there)."""
    lo, hi = fit_stretch
    if not (0.0 < lo < hi) or n_points < 8:
        raise InputError(f"refit stretch range {fit_stretch} / {n_points} points: need "
                         "0 < lo < hi and at least 8 points")
    g = np.linspace(lo, hi, n_points)
    return g[np.abs(g - 1.0) > 1e-9]


@dataclass(frozen=True)
class Refit:
    """Result of one refit (JSON-able through :meth:`to_dict`)."""

    tissue: str
    delta: float
    mu_MPa: tuple[float, ...]
    alpha: tuple[float, ...]
    nu: float
    fit_rms_pct: float
    fit_max_pct: float
    mu_vs_scaled_pct: float
    alpha_change_pct: float
    stable: bool
    unstable: dict[str, list[tuple[float, float]]]
    stability_stretch: tuple[float, float]
    fit_stretch: tuple[float, float]
    n_points: int
    n_starts: int
    poor: bool
    problem: str  # "" when usable, else why not (poor fit / unstable / invalid set)

    @property
    def ok(self) -> bool:
        return not self.problem

    def material(self) -> Ogden:
        return Ogden(self.mu_MPa, self.alpha, nu=self.nu)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["mu_MPa"] = list(self.mu_MPa)
        d["alpha"] = list(self.alpha)
        d["unstable"] = {k: [list(iv) for iv in v] for k, v in self.unstable.items()}
        d["stability_stretch"] = list(self.stability_stretch)
        d["fit_stretch"] = list(self.fit_stretch)
        d["ok"] = self.ok
        return d


def _starts(mu0: np.ndarray, al0: np.ndarray, n_starts: int) -> list[np.ndarray]:
    rng = np.random.default_rng(12345)
    out = [np.concatenate([mu0, al0])]
    for _ in range(max(n_starts, 1) - 1):
        out.append(np.concatenate([mu0 * rng.uniform(0.7, 1.3, mu0.size),
                                   al0 * rng.uniform(0.8, 1.2, al0.size)]))
    return out


def refit_scaled(base: Ogden, delta: float, *, tissue: str = "tissue",
                 fit_stretch: tuple[float, float] = (0.6, 1.5), n_points: int = 46,
                 stability_stretch: tuple[float, float] = (0.5, 2.0), n_starts: int = 6,
                 max_fit_error_pct: float = 1.0) -> Refit:
    """Re-fit an N = 3 Ogden set to the baseline uniaxial curve of ``base`` scaled by
    (1 + ``delta``) (delta as a fraction, e.g. 0.1 for +10 %). See the module docstring.
    Deterministic; results are memoised per process (same inputs -> the same Refit)."""
    return _refit_cached(tuple(base.mu_MPa), tuple(base.alpha),
                         float(base.nu if base.nu is not None else 0.49), float(delta), tissue,
                         tuple(float(x) for x in fit_stretch), int(n_points),
                         tuple(float(x) for x in stability_stretch), int(n_starts),
                         float(max_fit_error_pct))


@functools.lru_cache(maxsize=256)
def _refit_cached(mu_base, alpha_base, nu, delta, tissue, fit_stretch, n_points,
                  stability_stretch, n_starts, max_fit_error_pct) -> Refit:
    from scipy.optimize import least_squares

    base = Ogden(mu_base, alpha_base, nu=nu)

    if len(base.mu_MPa) != N_TERMS:
        raise InputError(f"{tissue}: refit expects an N = {N_TERMS} Ogden set, got "
                         f"{len(base.mu_MPa)} terms")
    if not (math.isfinite(delta) and delta > -1.0):
        raise InputError(f"{tissue}: perturbation {delta!r} must be > -100 %")
    lam = stretch_grid(fit_stretch, n_points)
    mu0 = np.array(base.mu_MPa)
    al0 = np.array(base.alpha)
    target = (1.0 + delta) * uniaxial_nominal_stress(mu0, al0, lam)
    w = np.maximum(np.abs(target), 0.05 * np.max(np.abs(target)))
    n = N_TERMS
    mmax = float(np.max(np.abs(mu0)))
    lo = np.concatenate([np.full(n, -10 * mmax), np.where(al0 > 0, 0.5, -20.0)])
    hi = np.concatenate([np.full(n, 10 * mmax), np.where(al0 > 0, 20.0, -0.5)])
    scale = np.concatenate([np.maximum(np.abs(mu0), 1e-3 * mmax), np.abs(al0)])

    def resid(x):
        return (uniaxial_nominal_stress(x[:n], x[n:], lam) - target) / w

    ln = np.log(lam)

    def jac(x):
        J = np.empty((lam.size, 2 * n))
        for i in range(n):
            m, a = x[i], x[n + i]
            t1, t2 = lam ** (a - 1.0), lam ** (-0.5 * a - 1.0)
            J[:, i] = 2.0 / a * (t1 - t2)
            J[:, n + i] = 2.0 * m * (-(t1 - t2) / a**2 + (ln * t1 + 0.5 * ln * t2) / a)
        return J / w[:, None]

    best = None
    for x0 in _starts(mu0, al0, n_starts):
        x0 = np.clip(x0, lo + 1e-12, hi - 1e-12)
        r = least_squares(resid, x0, jac=jac, bounds=(lo, hi), x_scale=scale, method="trf",
                          xtol=1e-10, ftol=1e-12, gtol=1e-10, max_nfev=300)
        if best is None or r.cost < best.cost:
            best = r
    x = best.x
    res = resid(x)
    rms = float(np.sqrt(np.mean(res**2)) * 100.0)
    mx = float(np.max(np.abs(res)) * 100.0)
    mu, al = tuple(float(v) for v in x[:n]), tuple(float(v) for v in x[n:])
    scaled = (1.0 + delta) * mu0
    mu_vs = float(np.max(np.abs(np.array(mu) - scaled)) / np.max(np.abs(scaled)) * 100.0)
    al_ch = float(np.max(np.abs(np.array(al) - al0) / np.abs(al0)) * 100.0)
    problems = []
    poor = mx > max_fit_error_pct
    if poor:
        problems.append(f"poor fit: max weighted error {mx:.3g} % > {max_fit_error_pct:g} %")
    stable, unstable = False, {}
    if sum(mu) <= 0.0:
        problems.append(f"invalid set: mu0 = sum(mu_i) = {sum(mu):.4g} MPa <= 0")
    else:
        rep = drucker_stability(Ogden(mu, al, nu=nu), stretch_range=stability_stretch,
                                n=301, incompressible=True)
        stable, unstable = rep.stable, rep.unstable
        if not stable:
            where = "; ".join(f"{m} {a:.3f}-{b:.3f}" for m, ivs in unstable.items()
                              for a, b in ivs)
            problems.append(f"Drucker-unstable (incompressible): {where}")
    return Refit(tissue=tissue, delta=float(delta), mu_MPa=mu, alpha=al, nu=nu,
                 fit_rms_pct=rms, fit_max_pct=mx, mu_vs_scaled_pct=mu_vs,
                 alpha_change_pct=al_ch, stable=stable, unstable=unstable,
                 stability_stretch=tuple(stability_stretch), fit_stretch=tuple(fit_stretch),
                 n_points=int(lam.size), n_starts=int(n_starts), poor=poor,
                 problem="; ".join(problems))

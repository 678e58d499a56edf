"""Hyperelastic material laws (units: MPa for moduli and stresses, stretches dimensionless).

Every law is a small frozen dataclass written in the split form

    W(F) = W_dev(F) + kappa/2 * G(J)^2,

where ``W_dev`` holds everything but the stiff volumetric part, ``G`` measures volume change
(``J - 1`` or ``ln J``) and ``kappa`` (MPa) is the bulk-like modulus. The split gives the
mixed displacement-pressure ("hybrid") form used by :mod:`handfe.solver`,

    Pi(u, p) = W_dev(F) + p G(J) - p^2 / (2 kappa),

which is equivalent for finite kappa and exactly incompressible when ``1/kappa = 0``.

Each law provides
- ``w_dev(F, c)``: UFL deviatoric energy, with parameters ``c`` taken from a
  :class:`BoundMaterial` (``dolfinx.fem.Constant`` values, so a parameter sweep never recompiles);
- ``w_dev_np(l1, l2, l3)`` and ``dw_dev_np(l1, l2, l3)``: NumPy energy and its derivatives with
  respect to the principal stretches, used for homogeneous deformations (:func:`homogeneous`).

Sign convention: tension positive; nominal (first Piola-Kirchhoff) stress = force per reference
area.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np

from handfe.errors import InputError
from handfe.paths import REFERENCE_DIR

MODES = ("uniaxial", "equibiaxial", "shear")
#: ... and confined compression (uniaxial strain: stretches (lambda, 1, 1), J = lambda), the
#: state of a tissue layer squeezed between a bone and an object; compressible laws only
HOMOGENEOUS_MODES = MODES + ("confined",)


def _check_nu(nu: float, law: str) -> None:
    if not (-1.0 < nu < 0.5):
        raise InputError(f"{law}: Poisson's ratio nu = {nu:g} must lie in (-1, 0.5); "
                         "use incompressible=True for the incompressible limit")


def _check_positive(name: str, value: float, law: str) -> None:
    if not (math.isfinite(value) and value > 0.0):
        raise InputError(f"{law}: {name} = {value!r} must be a positive finite number")


def lame_from_E_nu(E_MPa: float, nu: float, law: str) -> tuple[float, float]:
    """(mu, lmbda) in MPa from Young's modulus and Poisson's ratio, both validated."""
    _check_positive("E_MPa", E_MPa, law)
    _check_nu(nu, law)
    return E_MPa / (2 * (1 + nu)), E_MPa * nu / ((1 + nu) * (1 - 2 * nu))


def bulk_from_nu(mu0_MPa: float, nu: float) -> float:
    """Bulk modulus K = 2 mu0 (1 + nu) / (3 (1 - 2 nu)) in MPa (= 2/D1 of the Abaqus form)."""
    return 2.0 * mu0_MPa * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))


# --------------------------------------------------------------------------------------------
# Principal-stretch machinery for Ogden in UFL
# --------------------------------------------------------------------------------------------
# Sum of f(c_i) over the eigenvalues c_i of the isochoric right Cauchy-Green tensor Cbar,
# f(c) = c^(alpha/2). Two branches, chosen per quadrature point with ufl.conditional:
#  * Cardano/trigonometric eigenvalues when the deviatoric part D = Cbar - q I is not small;
#    the cosine argument is clamped to +-(1 - 1e-10) so acos and its derivative stay finite when
#    two stretches coincide (there dr/dC = 0, so the stress is exact);
#  * near the isotropic state (|D| small, e.g. the undeformed configuration) an exact
#    expansion in invariants: sum f(c_i) = 3 f(q) + f''(q)/2 tr D^2 + f'''(q)/6 tr D^3
#    + f''''(q)/24 (tr D^2)^2/2 + O(|D|^5) (tr D^4 = (tr D^2)^2/2 for a traceless symmetric 3x3).
#    It is a polynomial in the invariants: finite, exact and smoothly differentiable at Cbar = I,
#    so the residual vanishes to round-off there and Newton starts with the exact tangent.
# The switch sits at p = sqrt(tr D^2 / 6) = 1e-3, where the truncation error (~p^5) is below
# round-off and Cardano is well conditioned.
_TAYLOR_SWITCH = 1.0e-3
_ACOS_CLAMP = 1.0 - 1.0e-10


def _ufl_sum_powers(Cbar, exponents_half: list) -> list:
    """For each e in exponents_half return the UFL expression sum_i c_i^e (c_i eigenvalues of
    the symmetric positive definite 3x3 tensor Cbar)."""
    import ufl

    Id = ufl.Identity(3)
    q = ufl.tr(Cbar) / 3.0
    D = Cbar - q * Id
    t2 = ufl.inner(D, D)
    t3 = ufl.tr(D * D * D)
    p2 = t2 / 6.0
    p = ufl.sqrt(p2 + 1.0e-30)
    B = D / p
    r = ufl.det(B) / 2.0
    r = ufl.max_value(ufl.min_value(r, _ACOS_CLAMP), -_ACOS_CLAMP)
    phi = ufl.acos(r) / 3.0
    c1 = q + 2.0 * p * ufl.cos(phi)
    c3 = q + 2.0 * p * ufl.cos(phi + 2.0 * math.pi / 3.0)
    c2 = 3.0 * q - c1 - c3
    small = ufl.lt(p2, _TAYLOR_SWITCH**2)
    out = []
    for e in exponents_half:
        cardano = c1**e + c2**e + c3**e
        f0 = q**e
        f2 = e * (e - 1.0) * q ** (e - 2.0)
        f3 = e * (e - 1.0) * (e - 2.0) * q ** (e - 3.0)
        f4 = e * (e - 1.0) * (e - 2.0) * (e - 3.0) * q ** (e - 4.0)
        taylor = 3.0 * f0 + f2 / 2.0 * t2 + f3 / 6.0 * t3 + f4 / 24.0 * t2 * t2 / 2.0
        out.append(ufl.conditional(small, taylor, cardano))
    return out


# --------------------------------------------------------------------------------------------
# Laws
# --------------------------------------------------------------------------------------------
class Material:
    """Base class: the split-form interface described in the module docstring."""

    law: ClassVar[str] = "material"
    #: "J-1" or "lnJ": the volumetric measure G(J)
    vol_measure: ClassVar[str] = "J-1"
    #: whether the law has a volumetric/deviatoric split (mixed u-p form allowed)
    supports_mixed: ClassVar[bool] = True

    # -- parameters ---------------------------------------------------------------------------
    def parameters(self) -> dict[str, np.ndarray]:
        """Parameter arrays passed to ``w_dev`` (as fem.Constant when bound to a mesh)."""
        raise NotImplementedError

    @property
    def bulk_modulus_MPa(self) -> float:
        raise NotImplementedError

    @property
    def shear_modulus_MPa(self) -> float:
        """Initial (small-strain) shear modulus mu0."""
        raise NotImplementedError

    @property
    def youngs_modulus_MPa(self) -> float:
        mu, k = self.shear_modulus_MPa, self.bulk_modulus_MPa
        return 9.0 * k * mu / (3.0 * k + mu) if math.isfinite(k) else 3.0 * mu

    # -- UFL ------------------------------------------------------------------------------------
    def w_dev(self, F, c: Mapping[str, Any]):
        raise NotImplementedError

    def vol_G(self, J):
        import ufl

        return ufl.ln(J) if self.vol_measure == "lnJ" else J - 1.0

    def strain_energy(self, F, c: Mapping[str, Any] | None = None):
        """Full UFL strain energy W(F) per reference volume (MPa)."""
        import ufl

        c = c if c is not None else {k: _as_ufl(v) for k, v in self.parameters().items()}
        G = self.vol_G(ufl.det(F))
        return self.w_dev(F, c) + 0.5 * c["kappa"] * G * G

    # -- NumPy (principal stretches, arrays broadcast) ----------------------------------------
    def w_dev_np(self, l1, l2, l3):
        raise NotImplementedError

    def dw_dev_np(self, l1, l2, l3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """dW_dev/dlambda_i (MPa)."""
        raise NotImplementedError

    def energy_np(self, l1, l2, l3, *, incompressible: bool = False):
        W = self.w_dev_np(l1, l2, l3)
        if incompressible:
            return W
        J = l1 * l2 * l3
        G = np.log(J) if self.vol_measure == "lnJ" else J - 1.0
        return W + 0.5 * self.bulk_modulus_MPa * G * G

    def principal_nominal_stress_np(self, l1, l2, l3) -> tuple[np.ndarray, ...]:
        """P_i = dW/dlambda_i (compressible, full energy), MPa."""
        d = self.dw_dev_np(l1, l2, l3)
        J = l1 * l2 * l3
        if self.vol_measure == "lnJ":
            G, dG = np.log(J), 1.0 / J
        else:
            G, dG = J - 1.0, 1.0
        k = self.bulk_modulus_MPa
        vol = k * G * dG * J  # dU/dlambda_i = vol / lambda_i
        return tuple(di + vol / li for di, li in zip(d, (l1, l2, l3), strict=True))

    def with_params(self, **changes: Any) -> Material:
        """A copy with some parameters replaced (validated again)."""
        names = {f.name for f in fields(self)}  # type: ignore[arg-type]
        bad = set(changes) - names
        if bad:
            raise InputError(f"{self.law}: unknown parameter '{sorted(bad)[0]}' "
                             f"(parameters: {', '.join(sorted(names))})")
        kw = {f.name: getattr(self, f.name) for f in fields(self)}  # type: ignore[arg-type]
        kw.update(changes)
        return type(self)(**kw)


def _as_ufl(v):
    import ufl

    a = np.asarray(v, dtype=float)
    if a.ndim == 0:
        return float(a)
    return ufl.as_vector([float(x) for x in a])


def _isochoric(l1, l2, l3):
    Jm13 = (l1 * l2 * l3) ** (-1.0 / 3.0)
    return l1 * Jm13, l2 * Jm13, l3 * Jm13


def _chain_isochoric(dbar, l1, l2, l3):
    """dW/dlambda_i from dW/dlambdabar_j for lambdabar = J^(-1/3) lambda."""
    lam = (l1, l2, l3)
    Jm13 = (l1 * l2 * l3) ** (-1.0 / 3.0)
    # dlbar_j/dl_i = J^(-1/3) (delta_ij - l_j / (3 l_i))
    s = sum(db * lj for db, lj in zip(dbar, lam, strict=True))
    return tuple(Jm13 * (dbar[i] - s / (3.0 * lam[i])) for i in range(3))


@dataclass(frozen=True)
class Ogden(Material):
    """N-term Ogden law in the Abaqus form (brief S1):

    W = sum_i 2 mu_i / alpha_i^2 (lb1^a_i + lb2^a_i + lb3^a_i - 3) + (1/D1)(J - 1)^2,

    lb_k = J^(-1/3) lambda_k the deviatoric principal stretches, mu0 = sum mu_i (MPa),
    D1 = 3 (1 - 2 nu) / (mu0 (1 + nu)), kappa = 2/D1. Give ``nu`` (default 0.49) or ``D1_per_MPa``.
    The eigenvalue treatment that keeps W finite and exact at Cbar = I and at coincident stretches
    is described at :func:`_ufl_sum_powers`.
    """

    mu_MPa: tuple[float, ...]
    alpha: tuple[float, ...]
    nu: float | None = 0.49
    D1_per_MPa: float | None = None

    law: ClassVar[str] = "ogden"

    def __post_init__(self) -> None:
        mu = tuple(float(x) for x in self.mu_MPa)
        al = tuple(float(x) for x in self.alpha)
        object.__setattr__(self, "mu_MPa", mu)
        object.__setattr__(self, "alpha", al)
        if len(mu) == 0 or len(mu) != len(al):
            raise InputError(f"ogden: mu_MPa ({len(mu)} values) and alpha ({len(al)} values) "
                             "must be non-empty and of equal length")
        for i, (m, a) in enumerate(zip(mu, al, strict=True)):
            if not (math.isfinite(m) and math.isfinite(a)) or a == 0.0:
                raise InputError(f"ogden: term {i + 1}: mu = {m!r}, alpha = {a!r}: alpha must be "
                                 "non-zero and both finite")
        mu0 = sum(mu)
        if not mu0 > 0.0:
            raise InputError(f"ogden: initial shear modulus mu0 = sum(mu_i) = {mu0:g} MPa must be "
                             "positive (mu_MPa = " + ", ".join(f"{m:g}" for m in mu) + ")")
        if self.D1_per_MPa is not None:
            if self.nu is not None and self.nu != 0.49:
                raise InputError("ogden: give either nu or D1_per_MPa, not both")
            object.__setattr__(self, "nu", None)
            if not (self.D1_per_MPa > 0.0 and math.isfinite(self.D1_per_MPa)):
                raise InputError(f"ogden: D1_per_MPa = {self.D1_per_MPa!r} must be positive")
        else:
            _check_nu(float(self.nu if self.nu is not None else 0.49), "ogden")

    @property
    def shear_modulus_MPa(self) -> float:
        return sum(self.mu_MPa)

    @property
    def bulk_modulus_MPa(self) -> float:
        if self.D1_per_MPa is not None:
            return 2.0 / self.D1_per_MPa
        return bulk_from_nu(self.shear_modulus_MPa, float(self.nu))  # type: ignore[arg-type]

    def parameters(self) -> dict[str, np.ndarray]:
        return {"mu": np.array(self.mu_MPa), "alpha": np.array(self.alpha),
                "kappa": np.array(self.bulk_modulus_MPa)}

    def w_dev(self, F, c):
        import ufl

        J = ufl.det(F)
        Cbar = J ** (-2.0 / 3.0) * F.T * F
        n = len(self.mu_MPa)
        sums = _ufl_sum_powers(Cbar, [c["alpha"][i] / 2.0 for i in range(n)])
        return sum(2.0 * c["mu"][i] / c["alpha"][i] ** 2 * (sums[i] - 3.0) for i in range(n))

    def w_dev_np(self, l1, l2, l3):
        b = _isochoric(l1, l2, l3)
        return sum(2.0 * m / a**2 * (b[0] ** a + b[1] ** a + b[2] ** a - 3.0)
                   for m, a in zip(self.mu_MPa, self.alpha, strict=True))

    def dw_dev_np(self, l1, l2, l3):
        b = _isochoric(l1, l2, l3)
        dbar = [sum(2.0 * m / a * bj ** (a - 1.0) for m, a in zip(self.mu_MPa, self.alpha,
                                                                     strict=True)) for bj in b]
        return _chain_isochoric(dbar, l1, l2, l3)

    # -- literature sets ------------------------------------------------------------------------
    @classmethod
    def _from_reference(cls, key: str, nu: float) -> Ogden:
        data = json.loads((REFERENCE_DIR / "soft_tissue_ogden.json").read_text())
        return cls(tuple(data[key]["mu_MPa"]), tuple(data[key]["alpha"]), nu=nu)

    @classmethod
    def skin(cls, nu: float = 0.49) -> Ogden:
        """Human skin, Ogden N=3, uniaxial tension fit (brief S1; reference/soft_tissue_ogden.json,
        "skin"). The source gives no nu; 0.49 (near-incompressible, as the brief's fingertip
        fit)."""
        return cls._from_reference("skin", nu)

    @classmethod
    def subcutaneous(cls, nu: float = 0.49) -> Ogden:
        """Subcutaneous fat, Ogden N=3, uniaxial tension fit (brief S1;
        reference/soft_tissue_ogden.json, "subcutaneous"); nu as for :meth:`skin`."""
        return cls._from_reference("subcutaneous", nu)


@dataclass(frozen=True)
class MooneyRivlin(Material):
    """Two-term Mooney-Rivlin-type law with a second-order I1 term (brief S3), in isochoric
    invariants:

    W = C10 (Ib1 - 3) + C01 (Ib2 - 3) + C20 (Ib1 - 3)^2 + (1/D1)(J - 1)^2,

    mu0 = 2 (C10 + C01) (MPa), kappa = 2/D1 from ``nu`` (default 0.49).
    """

    C10_MPa: float = 0.0
    C01_MPa: float = 0.0
    C20_MPa: float = 0.0
    nu: float = 0.49

    law: ClassVar[str] = "mooney-rivlin"

    def __post_init__(self) -> None:
        for name in ("C10_MPa", "C01_MPa", "C20_MPa"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise InputError(f"mooney-rivlin: {name} = {v!r} must be finite")
        if not self.shear_modulus_MPa > 0.0:
            raise InputError(f"mooney-rivlin: mu0 = 2 (C10 + C01) = {self.shear_modulus_MPa:g} MPa "
                             "must be positive")
        if self.C20_MPa < 0.0:
            raise InputError(f"mooney-rivlin: C20_MPa = {self.C20_MPa:g} must be >= 0")
        _check_nu(self.nu, "mooney-rivlin")

    @property
    def shear_modulus_MPa(self) -> float:
        return 2.0 * (self.C10_MPa + self.C01_MPa)

    @property
    def bulk_modulus_MPa(self) -> float:
        return bulk_from_nu(self.shear_modulus_MPa, self.nu)

    def parameters(self):
        return {"C10": np.array(self.C10_MPa), "C01": np.array(self.C01_MPa),
                "C20": np.array(self.C20_MPa), "kappa": np.array(self.bulk_modulus_MPa)}

    def w_dev(self, F, c):
        import ufl

        J = ufl.det(F)
        Cbar = J ** (-2.0 / 3.0) * F.T * F
        I1 = ufl.tr(Cbar)
        I2 = 0.5 * (I1 * I1 - ufl.inner(Cbar, Cbar))
        return c["C10"] * (I1 - 3.0) + c["C01"] * (I2 - 3.0) + c["C20"] * (I1 - 3.0) ** 2

    def w_dev_np(self, l1, l2, l3):
        b1, b2, b3 = (x**2 for x in _isochoric(l1, l2, l3))
        I1 = b1 + b2 + b3
        I2 = b1 * b2 + b2 * b3 + b1 * b3
        return self.C10_MPa * (I1 - 3) + self.C01_MPa * (I2 - 3) + self.C20_MPa * (I1 - 3) ** 2

    def dw_dev_np(self, l1, l2, l3):
        lb = _isochoric(l1, l2, l3)
        b = [x**2 for x in lb]
        I1 = b[0] + b[1] + b[2]
        dW_dI1 = self.C10_MPa + 2.0 * self.C20_MPa * (I1 - 3.0)
        dbar = [dW_dI1 * 2.0 * lb[j] + self.C01_MPa * 2.0 * lb[j] * (I1 - b[j]) for j in range(3)]
        return _chain_isochoric(dbar, l1, l2, l3)

    @classmethod
    def fingertip(cls, subject: str = "mean", nu: float = 0.49) -> MooneyRivlin:
        """Homogeneous fingertip fit to 15-degree plate compression (brief S3;
        reference/fingertip_mooney_rivlin_fit.csv): C10 = 0, C01 and C20 per subject, nu = 0.49."""
        with (REFERENCE_DIR / "fingertip_mooney_rivlin_fit.csv").open() as fh:
            rows = {r["subject"]: r for r in csv.DictReader(fh)}
        if subject not in rows or subject == "std":
            raise InputError(f"mooney-rivlin fingertip preset: unknown subject '{subject}' "
                             f"(choose from {', '.join(k for k in rows if k != 'std')})")
        r = rows[subject]
        return cls(0.0, float(r["C01_kPa"]) * 1e-3, float(r["C20_kPa"]) * 1e-3, nu=nu)

    @classmethod
    def fingertip_mean(cls, nu: float = 0.49) -> MooneyRivlin:
        """The mean row of :meth:`fingertip`: C01 = 0.59 kPa, C20 = 2.65 kPa."""
        return cls.fingertip("mean", nu)


@dataclass(frozen=True)
class NeoHookean(Material):
    """Compressible neo-Hookean: W = mu/2 (I1 - 3) - mu ln J + lmbda/2 (ln J)^2 (MPa).

    Split: W_dev = mu/2 (I1 - 3) - mu ln J, G = ln J, kappa = lmbda (Lame's first parameter).
    """

    mu_MPa: float
    lmbda_MPa: float

    law: ClassVar[str] = "neo-hookean"
    vol_measure: ClassVar[str] = "lnJ"

    def __post_init__(self) -> None:
        _check_positive("mu_MPa", self.mu_MPa, self.law)
        if not (math.isfinite(self.lmbda_MPa) and self.lmbda_MPa > -2.0 / 3.0 * self.mu_MPa):
            raise InputError(f"neo-hookean: lmbda_MPa = {self.lmbda_MPa!r} gives a non-positive "
                             "bulk modulus")

    @classmethod
    def from_E_nu(cls, E_MPa: float, nu: float) -> NeoHookean:
        return cls(*lame_from_E_nu(E_MPa, nu, "neo-hookean"))

    @classmethod
    def layer(cls, name: str) -> NeoHookean:
        """Small-strain moduli of a fingertip layer (reference/fingertip_layers_2d.csv: stratum
        corneum, epidermis, dermis, subcutaneous, fingernail)."""
        with (REFERENCE_DIR / "fingertip_layers_2d.csv").open() as fh:
            rows = {r["layer"]: r for r in csv.DictReader(fh)}
        if name not in rows:
            raise InputError(f"neo-hookean layer preset: unknown layer '{name}' "
                             f"(choose from {', '.join(rows)})")
        return cls.from_E_nu(float(rows[name]["E_MPa"]), float(rows[name]["nu"]))

    @property
    def nu(self) -> float:
        return self.lmbda_MPa / (2.0 * (self.lmbda_MPa + self.mu_MPa))

    @property
    def shear_modulus_MPa(self) -> float:
        return self.mu_MPa

    @property
    def bulk_modulus_MPa(self) -> float:
        """kappa of the split W_dev + kappa/2 (ln J)^2, i.e. Lame's lmbda (not K)."""
        return self.lmbda_MPa

    @property
    def youngs_modulus_MPa(self) -> float:
        mu, lam = self.mu_MPa, self.lmbda_MPa
        return mu * (3 * lam + 2 * mu) / (lam + mu)

    def parameters(self):
        return {"mu": np.array(self.mu_MPa), "kappa": np.array(self.lmbda_MPa)}

    def w_dev(self, F, c):
        import ufl

        return 0.5 * c["mu"] * (ufl.tr(F.T * F) - 3.0) - c["mu"] * ufl.ln(ufl.det(F))

    def w_dev_np(self, l1, l2, l3):
        mu = self.mu_MPa
        return 0.5 * mu * (l1**2 + l2**2 + l3**2 - 3.0) - mu * np.log(l1 * l2 * l3)

    def dw_dev_np(self, l1, l2, l3):
        return tuple(self.mu_MPa * (li - 1.0 / li) for li in (l1, l2, l3))


@dataclass(frozen=True)
class StVenantKirchhoff(Material):
    """St. Venant-Kirchhoff, for reference: W = lmbda/2 (tr E)^2 + mu tr(E^2), E = (C - I)/2.
    Not polyconvex (unstable in strong compression); no volumetric split (displacement only)."""

    mu_MPa: float
    lmbda_MPa: float

    law: ClassVar[str] = "st-venant-kirchhoff"
    supports_mixed: ClassVar[bool] = False

    def __post_init__(self) -> None:
        _check_positive("mu_MPa", self.mu_MPa, self.law)
        if not math.isfinite(self.lmbda_MPa):
            raise InputError(f"st-venant-kirchhoff: lmbda_MPa = {self.lmbda_MPa!r} must be finite")

    @classmethod
    def from_E_nu(cls, E_MPa: float, nu: float) -> StVenantKirchhoff:
        return cls(*lame_from_E_nu(E_MPa, nu, "st-venant-kirchhoff"))

    @classmethod
    def nail(cls) -> StVenantKirchhoff:
        """Fingernail, E = 170 MPa, nu = 0.3 (brief S1; reference/soft_tissue_ogden.json)."""
        return cls.from_E_nu(170.0, 0.3)

    @property
    def shear_modulus_MPa(self) -> float:
        return self.mu_MPa

    @property
    def bulk_modulus_MPa(self) -> float:
        return self.lmbda_MPa + 2.0 / 3.0 * self.mu_MPa

    def parameters(self):
        return {"mu": np.array(self.mu_MPa), "lmbda": np.array(self.lmbda_MPa),
                "kappa": np.array(0.0)}

    def w_dev(self, F, c):
        import ufl

        E = 0.5 * (F.T * F - ufl.Identity(3))
        return 0.5 * c["lmbda"] * ufl.tr(E) ** 2 + c["mu"] * ufl.inner(E, E)

    def w_dev_np(self, l1, l2, l3):
        E = [(li**2 - 1.0) / 2.0 for li in (l1, l2, l3)]
        trE = E[0] + E[1] + E[2]
        return 0.5 * self.lmbda_MPa * trE**2 + self.mu_MPa * (E[0] ** 2 + E[1] ** 2 + E[2] ** 2)

    def dw_dev_np(self, l1, l2, l3):
        lam = (l1, l2, l3)
        E = [(li**2 - 1.0) / 2.0 for li in lam]
        trE = E[0] + E[1] + E[2]
        return tuple((self.lmbda_MPa * trE + 2.0 * self.mu_MPa * E[i]) * lam[i] for i in range(3))

    def principal_nominal_stress_np(self, l1, l2, l3):
        return self.dw_dev_np(l1, l2, l3)

    def energy_np(self, l1, l2, l3, *, incompressible: bool = False):
        return self.w_dev_np(l1, l2, l3)  # no volumetric split: W_dev is the whole energy


LAWS: dict[str, type[Material]] = {
    "ogden": Ogden, "mooney-rivlin": MooneyRivlin, "neo-hookean": NeoHookean,
    "st-venant-kirchhoff": StVenantKirchhoff,
}

PRESETS: dict[str, dict[str, Callable[[], Material]]] = {
    "ogden": {"skin": Ogden.skin, "subcutaneous": Ogden.subcutaneous},
    "mooney-rivlin": {"fingertip": MooneyRivlin.fingertip_mean,
                      **{f"fingertip-{s}": (lambda s=s: MooneyRivlin.fingertip(s))
                         for s in ("S1", "S2", "S3", "S4", "S5")}},
    "neo-hookean": {name: (lambda n=name: NeoHookean.layer(n))
                    for name in ("stratum_corneum", "epidermis", "dermis", "subcutaneous",
                                 "fingernail")},
    "st-venant-kirchhoff": {"nail": StVenantKirchhoff.nail},
}


def preset(law: str, name: str) -> Material:
    """A literature set by law and preset name; unknown names raise InputError listing choices."""
    if law not in PRESETS:
        raise InputError(f"unknown material law '{law}' (choose from {', '.join(PRESETS)})")
    if name not in PRESETS[law]:
        raise InputError(f"unknown {law} preset '{name}' (choose from {', '.join(PRESETS[law])})")
    return PRESETS[law][name]()


# --------------------------------------------------------------------------------------------
# Binding to a mesh: parameters as fem.Constant
# --------------------------------------------------------------------------------------------
class BoundMaterial:
    """A material whose parameters live in ``dolfinx.fem.Constant`` objects on a mesh, so that
    :meth:`assign` changes values without recompiling forms. ``inv_kappa`` (1/kappa, 1/MPa) is a
    constant too; 0 means exactly incompressible."""

    def __init__(self, material: Material, mesh, *, incompressible: bool = False):
        from dolfinx import fem
        from petsc4py import PETSc

        self.material = material
        self.incompressible = incompressible
        self.c: dict[str, Any] = {}
        for k, v in material.parameters().items():
            self.c[k] = fem.Constant(mesh, PETSc.ScalarType(np.asarray(v, dtype=float)))
        self.inv_kappa = fem.Constant(mesh, PETSc.ScalarType(0.0))
        self._set_inv_kappa()

    def _set_inv_kappa(self) -> None:
        k = self.material.bulk_modulus_MPa
        self.inv_kappa.value = 0.0 if (self.incompressible or k <= 0.0) else 1.0 / k
        if self.incompressible:
            self.c["kappa"].value = 0.0

    def assign(self, material: Material) -> None:
        """Replace parameter values by those of ``material`` (same law and term count)."""
        if type(material) is not type(self.material):
            raise InputError(f"cannot assign a {material.law} to a bound {self.material.law}")
        new = material.parameters()
        for k, v in new.items():
            if np.shape(v) != np.shape(self.c[k].value):
                raise InputError(f"{material.law}: parameter '{k}' has shape {np.shape(v)}, "
                                 f"bound shape {np.shape(self.c[k].value)}")
            self.c[k].value = np.asarray(v, dtype=float)
        self.material = material
        self._set_inv_kappa()

    def strain_energy(self, F):
        """Displacement-form energy W(F) (exact incompressibility is not available here)."""
        return self.material.strain_energy(F, self.c)

    def mixed_energy(self, F, p):
        """Perturbed-Lagrangian energy W_dev + p G(J) - p^2 inv_kappa / 2 (u-p form)."""
        import ufl

        if not self.material.supports_mixed:
            raise InputError(f"{self.material.law} has no volumetric split: use a displacement "
                             "formulation")
        G = self.material.vol_G(ufl.det(F))
        return self.material.w_dev(F, self.c) + p * G - 0.5 * self.inv_kappa * p * p

    def first_piola(self, F, p=None):
        """Nominal stress tensor P = dW/dF (MPa) as UFL; with ``p`` from the mixed form."""
        import ufl

        F = ufl.variable(F)
        W = self.strain_energy(F) if p is None else self.mixed_energy(F, p)
        return ufl.diff(W, F)


# --------------------------------------------------------------------------------------------
# Homogeneous deformations: closed form, tangent, Drucker stability
# --------------------------------------------------------------------------------------------
def _lateral_free(mat: Material, lam: float, mode: str) -> float:
    """Traction-free lateral stretch for a compressible law (solves P_lateral = 0)."""
    from scipy.optimize import brentq

    def stretches(s):
        if mode == "uniaxial":
            return lam, s, s
        if mode == "equibiaxial":
            return lam, lam, s
        return lam, 1.0, s

    idx = 1 if mode == "uniaxial" else 2

    def f(s):
        return mat.principal_nominal_stress_np(*stretches(s))[idx]

    lo, hi = 1e-3, 1e3
    # the lateral stress is monotone in s for all laws here: bracket and solve
    return brentq(f, lo, hi, xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=500)


def check_homogeneous_mode(mode: str, incompressible: bool) -> None:
    """Refuse an unknown mode, and confined compression with exact incompressibility."""
    if mode not in HOMOGENEOUS_MODES:
        raise InputError(f"unknown mode '{mode}' (choose from {', '.join(HOMOGENEOUS_MODES)})")
    if mode == "confined" and incompressible:
        raise InputError("confined compression changes the volume (J = stretch): not with "
                         "exact incompressibility")


def homogeneous(mat: Material, mode: str, lam: float, *,
                incompressible: bool = False) -> tuple[float, tuple[float, float, float]]:
    """Nominal stress P11 (MPa) along the loading direction for a homogeneous deformation with
    stretch ``lam`` (> 0), and the three principal stretches.

    Modes: ``uniaxial`` (lambda, s, s), ``equibiaxial`` (lambda, lambda, s) - the stress reported
    is P11 = P22 - and ``shear`` = pure shear / planar tension (lambda, 1, s); ``s`` makes the free
    faces traction-free, or is fixed by J = 1 when ``incompressible``. ``confined`` = uniaxial
    strain (lambda, 1, 1): the volume changes with lambda, so compressible laws only.
    """
    check_homogeneous_mode(mode, incompressible)
    if not (math.isfinite(lam) and lam > 0.0):
        raise InputError(f"stretch must be positive and finite, got {lam!r}")
    if mode == "confined":
        st = (lam, 1.0, 1.0)
        return float(mat.principal_nominal_stress_np(*st)[0]), st
    if incompressible:
        if not mat.supports_mixed:
            raise InputError(f"{mat.law} has no incompressible form")
        s = {"uniaxial": lam**-0.5, "equibiaxial": lam**-2.0, "shear": 1.0 / lam}[mode]
        st = {"uniaxial": (lam, s, s), "equibiaxial": (lam, lam, s), "shear": (lam, 1.0, s)}[mode]
        d = mat.dw_dev_np(*st)
        lat = 1 if mode == "uniaxial" else 2
        p = d[lat] * st[lat]  # Lagrange multiplier making the free direction traction-free
        return float(d[0] - p / st[0]), st
    s = _lateral_free(mat, lam, mode)
    st = {"uniaxial": (lam, s, s), "equibiaxial": (lam, lam, s), "shear": (lam, 1.0, s)}[mode]
    return float(mat.principal_nominal_stress_np(*st)[0]), st


def tangent(mat: Material, mode: str, lam: float, *, incompressible: bool = False) -> float:
    """dP11/dlambda along the mode's path (MPa), by a 4th-order central difference of the
    closed form (relative accuracy ~1e-9)."""
    h = 1e-4 * lam

    def P(x):
        return homogeneous(mat, mode, x, incompressible=incompressible)[0]

    return (-P(lam + 2 * h) + 8 * P(lam + h) - 8 * P(lam - h) + P(lam - 2 * h)) / (12 * h)


@dataclass(frozen=True)
class StabilityReport:
    """Where the tangent of the nominal stress is not positive, per mode, in [lo, hi]."""

    material: str
    incompressible: bool
    stretch_range: tuple[float, float]
    unstable: dict[str, list[tuple[float, float]]]

    @property
    def stable(self) -> bool:
        return not any(self.unstable.values())

    def describe(self) -> str:
        lines = [f"{self.material} ({'incompressible' if self.incompressible else 'compressible'}),"
                 f" stretch {self.stretch_range[0]:g}-{self.stretch_range[1]:g}:"]
        for mode, ivs in self.unstable.items():
            if not ivs:
                lines.append(f"  {mode}: Drucker-stable throughout")
            for a, b in ivs:
                lines.append(f"  {mode}: UNSTABLE (dP/dlambda <= 0) for stretch {a:.3f} to {b:.3f}")
        return "\n".join(lines)


def drucker_stability(mat: Material, *, stretch_range: tuple[float, float] = (0.5, 2.0),
                      n: int = 601, incompressible: bool = True,
                      modes: tuple[str, ...] = MODES) -> StabilityReport:
    """Scan ``n`` stretches of each mode and report intervals where dP/dlambda <= 0."""
    lo, hi = stretch_range
    if not (0.0 < lo < hi):
        raise InputError(f"stretch range {stretch_range}: need 0 < lo < hi")
    grid = np.linspace(lo, hi, n)
    out: dict[str, list[tuple[float, float]]] = {}
    name = mat.law
    for mode in modes:
        bad = np.array([tangent(mat, mode, float(x), incompressible=incompressible) <= 0.0
                        for x in grid])
        ivs = []
        i = 0
        while i < n:
            if bad[i]:
                j = i
                while j + 1 < n and bad[j + 1]:
                    j += 1
                ivs.append((float(grid[i]), float(grid[j])))
                i = j + 1
            else:
                i += 1
        out[mode] = ivs
    return StabilityReport(name, incompressible, (lo, hi), out)

"""Closed-form stress of each law against independent formulas (NumPy, 1e-8 relative),
parameter validation and the Drucker report."""

import numpy as np
import pytest

from handfe.errors import InputError
from handfe.materials import (
    MODES,
    MooneyRivlin,
    NeoHookean,
    Ogden,
    StVenantKirchhoff,
    drucker_stability,
    homogeneous,
    preset,
    tangent,
)

LAMS = np.linspace(0.6, 1.6, 11)


def ogden_incompressible(m: Ogden, mode: str, lam: float) -> float:
    """Textbook incompressible Ogden nominal stresses (Abaqus form)."""
    out = 0.0
    for mu, a in zip(m.mu_MPa, m.alpha, strict=True):
        k = 2 * mu / a
        if mode == "uniaxial":
            out += k * (lam ** (a - 1) - lam ** (-a / 2 - 1))
        elif mode == "equibiaxial":
            out += k * (lam ** (a - 1) - lam ** (-2 * a - 1))
        else:
            out += k * (lam ** (a - 1) - lam ** (-a - 1))
    return out


def mr_incompressible(m: MooneyRivlin, mode: str, lam: float) -> float:
    """P = 2 (lam - lat) (W1 + W2 ...) for the Mooney-Rivlin-type law (Ogden's book, ch. 7)."""
    if mode == "uniaxial":
        I1 = lam**2 + 2 / lam
        W1 = m.C10_MPa + 2 * m.C20_MPa * (I1 - 3)
        return 2 * (lam - lam**-2) * (W1 + m.C01_MPa / lam)
    if mode == "equibiaxial":
        I1 = 2 * lam**2 + lam**-4
        W1 = m.C10_MPa + 2 * m.C20_MPa * (I1 - 3)
        return 2 * (lam - lam**-5) * (W1 + lam**2 * m.C01_MPa)
    I1 = lam**2 + 1 + lam**-2
    W1 = m.C10_MPa + 2 * m.C20_MPa * (I1 - 3)
    return 2 * (lam - lam**-3) * (W1 + m.C01_MPa)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("mat", [Ogden.skin(), Ogden.subcutaneous()], ids=["skin", "subcut"])
def test_ogden_incompressible_closed_form(mat, mode):
    for lam in LAMS:
        P, st = homogeneous(mat, mode, lam, incompressible=True)
        ref = ogden_incompressible(mat, mode, lam)
        assert np.prod(st) == pytest.approx(1.0, abs=1e-14)
        assert P == pytest.approx(ref, rel=1e-8, abs=1e-14)


@pytest.mark.parametrize("mode", MODES)
def test_mooney_rivlin_incompressible_closed_form(mode):
    mat = MooneyRivlin(C10_MPa=0.0004, C01_MPa=0.00059, C20_MPa=0.00265)
    for lam in LAMS:
        P, _ = homogeneous(mat, mode, lam, incompressible=True)
        assert P == pytest.approx(mr_incompressible(mat, mode, lam), rel=1e-8, abs=1e-14)


def complex_step_stress(mat, st):
    """dW/dlambda_i by complex-step differentiation of the energy (exact to round-off):
    independent of the analytic derivative formulas in handfe.materials."""
    h = 1e-30
    out = []
    for i in range(3):
        z = [complex(x) for x in st]
        z[i] += 1j * h
        out.append(mat.energy_np(*[np.complex128(x) for x in z]).imag / h)
    return np.array(out)


COMPRESSIBLE = [Ogden.skin(), Ogden.subcutaneous(), MooneyRivlin.fingertip_mean(),
                NeoHookean.from_E_nu(0.05, 0.45), StVenantKirchhoff.from_E_nu(1.0, 0.3)]


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("mat", COMPRESSIBLE, ids=lambda m: m.law)
def test_compressible_closed_form(mat, mode):
    lams = LAMS if mat.law != "st-venant-kirchhoff" else np.linspace(0.8, 1.3, 6)
    for lam in lams:
        P, st = homogeneous(mat, mode, lam)
        Pcs = complex_step_stress(mat, st)
        scale = max(abs(Pcs[0]), 1e-3 * mat.shear_modulus_MPa)
        assert P == pytest.approx(Pcs[0], rel=1e-8, abs=1e-8 * scale)
        # the free directions are traction-free
        free = [1, 2] if mode == "uniaxial" else [2]
        for i in free:
            assert abs(Pcs[i]) < 1e-9 * max(abs(Pcs[0]), mat.shear_modulus_MPa)


def test_neo_hookean_uniaxial_independent_formula():
    """Compressible neo-Hookean uniaxial: P = mu (l - 1/l) + lmbda ln J / l with the lateral
    stretch from mu (s - 1/s) + lmbda ln J / s = 0 (solved here with Newton's method, not
    the library's bracketing solver)."""
    from scipy.optimize import newton

    mat = NeoHookean(mu_MPa=0.02, lmbda_MPa=0.3)
    for lam in LAMS:
        def lat(s, lam=lam):
            return mat.mu_MPa * (s - 1 / s) + mat.lmbda_MPa * np.log(lam * s * s) / s

        s = newton(lat, 1.0, tol=1e-15, maxiter=100)
        J = lam * s * s
        ref = mat.mu_MPa * (lam - 1 / lam) + mat.lmbda_MPa * np.log(J) / lam
        assert homogeneous(mat, "uniaxial", lam)[0] == pytest.approx(ref, rel=1e-8, abs=1e-14)


def test_small_strain_limit():
    """Initial slope of uniaxial P(lambda) = Young's modulus, 3 mu0 when incompressible."""
    m = Ogden.skin()
    assert tangent(m, "uniaxial", 1.0, incompressible=True) == pytest.approx(
        3 * m.shear_modulus_MPa, rel=1e-7)
    nh = NeoHookean.from_E_nu(0.05, 0.3)
    assert tangent(nh, "uniaxial", 1.0) == pytest.approx(0.05, rel=1e-7)


def test_reference_state_is_stress_free():
    for m in COMPRESSIBLE:
        for mode in MODES:
            assert homogeneous(m, mode, 1.0)[0] == pytest.approx(0.0, abs=1e-15)


def test_presets_cite_their_tables():
    skin = Ogden.skin()
    assert skin.mu_MPa == (-0.07594, 0.01138, 0.06572)
    assert skin.shear_modulus_MPa == pytest.approx(0.00116)
    mr = MooneyRivlin.fingertip_mean()
    assert (mr.C01_MPa, mr.C20_MPa) == pytest.approx((0.00059, 0.00265))
    assert StVenantKirchhoff.nail().youngs_modulus_MPa == pytest.approx(170.0)
    # D1 of the Abaqus form from nu: kappa = 2/D1 = 2 mu0 (1+nu) / (3 (1-2nu))
    assert skin.bulk_modulus_MPa == pytest.approx(2 * 0.00116 * 1.49 / (3 * 0.02))


@pytest.mark.parametrize("bad", [
    lambda: Ogden((-0.1, 0.01), (2.0, 3.0)),          # mu0 < 0
    lambda: Ogden((0.1,), (2.0, 3.0)),                # length mismatch
    lambda: Ogden((0.1,), (0.0,)),                    # alpha = 0
    lambda: Ogden.skin(nu=0.5),                       # nu >= 0.5
    lambda: NeoHookean.from_E_nu(1.0, 0.55),
    lambda: NeoHookean.from_E_nu(-1.0, 0.3),
    lambda: MooneyRivlin(C01_MPa=-0.001),
    lambda: preset("ogden", "bogus"),
    lambda: preset("rubber", "skin"),
    lambda: MooneyRivlin.fingertip("S9"),
    lambda: homogeneous(Ogden.skin(), "uniaxial", -0.5),
    lambda: homogeneous(Ogden.skin(), "torsion", 1.1),
    lambda: Ogden.skin().with_params(beta=1.0),
])
def test_bad_parameters_raise_clear_errors(bad):
    with pytest.raises(InputError):
        bad()


def test_error_message_names_value():
    with pytest.raises(InputError, match="nu = 0.5"):
        Ogden.skin(nu=0.5)
    with pytest.raises(InputError, match="'bogus'.*skin, subcutaneous"):
        preset("ogden", "bogus")


def test_drucker_report_brief_ogden_sets():
    """The brief's Ogden sets (mu_1 < 0): stable 0.5-2.0 when incompressible; at nu = 0.49 the
    equibiaxial compression branch loses stability below lambda ~ 0.57 (docs/materials.md)."""
    for m in (Ogden.skin(), Ogden.subcutaneous()):
        assert drucker_stability(m, n=151, incompressible=True).stable
        rep = drucker_stability(m, n=151, incompressible=False)
        assert rep.unstable["uniaxial"] == [] and rep.unstable["shear"] == []
        (lo, hi), = rep.unstable["equibiaxial"]
        assert lo == pytest.approx(0.5) and 0.55 < hi < 0.6


def test_drucker_flags_an_unstable_set():
    """A set whose negative term dominates in tension softens: the report must say where."""
    m = Ogden((0.01, -0.02, 0.012), (2.0, 4.0, 1.0))
    rep = drucker_stability(m, n=151, incompressible=True)
    assert not rep.stable
    assert "UNSTABLE" in rep.describe()


def test_confined_compression_small_strain_modulus_and_the_ogden_sets_bulk_limit():
    """Uniaxial strain (lambda, 1, 1): at small strain P11 / (lambda - 1) is the P-wave modulus
    kappa + 4 mu0 / 3; the brief's fat set at nu = 0.499 (kappa = 0.29 MPa) needs J ~ 0.2 to
    carry 0.3 MPa - a pad pressure of the muscle-driven grasps - in a confined layer, where
    nearly incompressible tissue would keep J ~ 1 (docs/grasp.md, twenty-fourth session)."""
    fat = Ogden.subcutaneous(nu=0.499)
    lam = 1.0 - 1e-6
    P, st = homogeneous(fat, "confined", lam)
    assert st == (lam, 1.0, 1.0)
    m = fat.bulk_modulus_MPa + 4.0 / 3.0 * fat.shear_modulus_MPa
    assert P / (lam - 1.0) == pytest.approx(m, rel=1e-4)
    assert fat.bulk_modulus_MPa == pytest.approx(0.29, rel=0.01)
    assert -homogeneous(fat, "confined", 0.2)[0] == pytest.approx(0.30, abs=0.01)
    with pytest.raises(InputError, match="volume"):
        homogeneous(fat, "confined", 0.5, incompressible=True)

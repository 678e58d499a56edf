"""The NumPy per-cell Ogden kernel (handfe.ogden_p1) against finite differences and against the
UFL form it replaces in the grasp problem (1 and 2 ranks)."""

import numpy as np
import pytest
from mpi4py import MPI

from handfe.materials import Ogden
from handfe.ogden_p1 import OgdenP1Kernel, ogden_dev_stress_tangent

pytestmark = pytest.mark.mpi

SKIN = Ogden.skin(nu=0.499)


def _w(F, mu, alpha):
    c = np.linalg.eigvalsh(F.T @ F)
    lb = np.sqrt(c) * np.linalg.det(F) ** (-1.0 / 3.0)
    return sum(2.0 * m / a**2 * ((lb**a).sum() - 3.0) for m, a in zip(mu, alpha, strict=True))


@pytest.mark.parametrize("F", [
    np.eye(3),                                   # three coincident eigenvalues
    np.diag([1.0, 1.0, 1.25]),                   # two coincident
    np.diag([0.6, 1.3, 1.3]),                    # compression, two coincident
    np.eye(3) + 1e-9 * np.arange(9.0).reshape(3, 3) / 9.0,   # nearly isotropic
    np.array([[1.1, 0.3, -0.1], [0.05, 0.8, 0.2], [0.1, -0.2, 1.2]]),  # general, J != 1
])
def test_stress_and_tangent_match_finite_differences(F):
    mu, alpha = np.array(SKIN.mu_MPa), np.array(SKIN.alpha)
    P, A = ogden_dev_stress_tangent(F[None], mu[None], alpha[None])
    h = 1e-6
    scale_p = max(np.abs(mu).max(), np.abs(P).max())
    for k in range(3):
        for ell in range(3):
            E = np.zeros((3, 3))
            E[k, ell] = h
            dW = (_w(F + E, mu, alpha) - _w(F - E, mu, alpha)) / (2 * h)
            assert P[0, k, ell] == pytest.approx(dW, abs=1e-7 * scale_p)
            Pp, _ = ogden_dev_stress_tangent((F + E)[None], mu[None], alpha[None])
            Pm, _ = ogden_dev_stress_tangent((F - E)[None], mu[None], alpha[None])
            np.testing.assert_allclose(A[0, :, :, k, ell], (Pp[0] - Pm[0]) / (2 * h),
                                       atol=1e-7 * np.abs(A).max())
    # small strain: A = mu0 (d_ik d_JL + d_iL d_Jk) - 2/3 mu0 d_iJ d_kL
    if np.allclose(F, np.eye(3)):
        I = np.eye(3)
        mu0 = SKIN.shear_modulus_MPa
        ref = mu0 * (np.einsum("ik,JL->iJkL", I, I) + np.einsum("iL,Jk->iJkL", I, I)) \
            - 2.0 / 3.0 * mu0 * np.einsum("iJ,kL->iJkL", I, I)
        np.testing.assert_allclose(A[0], ref, atol=1e-8 * mu0)


def test_kernel_forms_are_the_derivatives_of_the_energy():
    """Assembled over a distorted P1 mesh (1 or 2 ranks): the residual is the derivative of
    the total energy sum_c W(F_c) |c| and the Jacobian the derivative of the residual, both
    along a random direction (central differences). No UFL Ogden form is compiled: the one
    the kernel replaces takes minutes to compile."""
    import ufl
    from dolfinx import fem, mesh
    from dolfinx.fem import petsc as fp
    from petsc4py import PETSc

    comm = MPI.COMM_WORLD
    msh = mesh.create_unit_cube(comm, 3, 3, 3)
    V = fem.VectorFunctionSpace(msh, ("CG", 1))
    u = fem.Function(V)
    u.interpolate(lambda x: np.vstack([0.2 * x[1] * x[2], 0.1 * np.sin(3 * x[0]),
                                       -0.15 * x[0] * x[2]]))
    n = len(SKIN.mu_MPa)
    D = fem.VectorFunctionSpace(msh, ("DG", 0), dim=n)
    mu, alpha = fem.Function(D), fem.Function(D)
    mu.x.array[:] = np.tile(SKIN.mu_MPa, mu.x.array.size // n)
    alpha.x.array[:] = np.tile(SKIN.alpha, alpha.x.array.size // n)
    v, du = ufl.TestFunction(V), ufl.TrialFunction(V)
    dx1 = ufl.Measure("dx", domain=msh, metadata={"quadrature_degree": 1})
    k = OgdenP1Kernel(msh, u, mu, alpha, v, du, dx1)
    L, a = fem.form(k.residual), fem.form(k.jacobian)
    im = msh.topology.index_map(3)
    owned = np.arange(im.size_local, dtype=np.int32)
    X = msh.geometry.x[msh.geometry.dofmap.array.reshape(-1, 4)[owned]]  # (n, 4, 3)
    vol_c = np.abs(np.linalg.det(X[:, 1:] - X[:, :1])) / 6.0
    grad = fem.Expression(ufl.grad(u), np.array([[0.25, 0.25, 0.25]]))

    def energy():
        F = grad.eval(owned).reshape(-1, 3, 3) + np.eye(3)
        w = np.array([_w(f, SKIN.mu_MPa, SKIN.alpha) for f in F])
        return comm.allreduce(float(w @ vol_c), op=MPI.SUM)

    def residual():
        k.update(tangent=False)
        b = fp.assemble_vector(L)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return b

    rng = np.random.default_rng(comm.rank)
    e = u.vector.duplicate()
    e.setArray(rng.standard_normal(e.getLocalSize()))
    u0 = u.vector.copy()
    k.update()
    A = fp.assemble_matrix(a)
    A.assemble()
    b0 = residual()
    Ae = e.duplicate()
    A.mult(e, Ae)
    h = 1e-6
    out = []
    for s in (1.0, -1.0):
        u.vector.waxpy(s * h, e, u0)
        u.x.scatter_forward()
        out.append((energy(), residual()))
    dE = (out[0][0] - out[1][0]) / (2 * h)
    assert b0.dot(e) == pytest.approx(dE, rel=1e-6)
    db = out[0][1].copy()
    db.axpy(-1.0, out[1][1])
    db.scale(1.0 / (2 * h))
    db.axpy(-1.0, Ae)
    assert db.norm() <= 1e-6 * Ae.norm()


def _cube_kernel(mat: Ogden, cells: tuple[int, int, int]):
    """An :class:`OgdenP1Kernel` of ``mat`` on a unit cube of ``cells`` (one rank); returns it,
    the displacement and the parameter Functions (mu, alpha)."""
    import ufl
    from dolfinx import fem, mesh

    msh = mesh.create_unit_cube(MPI.COMM_SELF, *cells)
    V = fem.VectorFunctionSpace(msh, ("CG", 1))
    u = fem.Function(V)
    n = len(mat.mu_MPa)
    D = fem.VectorFunctionSpace(msh, ("DG", 0), dim=n)
    mu, alpha = fem.Function(D), fem.Function(D)
    mu.x.array[:] = np.tile(mat.mu_MPa, mu.x.array.size // n)
    alpha.x.array[:] = np.tile(mat.alpha, alpha.x.array.size // n)
    dx1 = ufl.Measure("dx", domain=msh, metadata={"quadrature_degree": 1})
    k = OgdenP1Kernel(msh, u, mu, alpha, ufl.TestFunction(V), ufl.TrialFunction(V), dx1)
    return k, u, mu, alpha


def test_kernel_shear_modulus_is_mu0_at_rest_and_mu_lambda_alpha_when_stretches_coincide():
    """The incremental shear modulus behind the tangent stabilisation of p1-p1s
    (:meth:`OgdenP1Kernel.shear_modulus`): sum mu_p = mu0 at rest and under a pure dilatation
    (isochoric stretches 1); for an isochoric state with two equal stretches it is the mean
    over the principal planes of mu_p lbar^alpha_p; under 50 % compression of the fat it is
    ~20 x mu0 (the pads' stiffening that the mu0-based term ignores)."""
    fat = Ogden.subcutaneous(nu=0.499)
    k, u, _, _ = _cube_kernel(fat, (1, 1, 1))
    mu0 = sum(fat.mu_MPa)

    def modulus(stretch) -> np.ndarray:
        s = np.asarray(stretch, dtype=float)
        u.interpolate(lambda x: (s[:, None] - 1.0) * x)
        return k.shear_modulus()

    np.testing.assert_allclose(modulus([1.0, 1.0, 1.0]), mu0, rtol=1e-12)
    np.testing.assert_allclose(modulus([0.8, 0.8, 0.8]), mu0, rtol=1e-9)
    lam = 0.5
    stretches = np.array([lam, lam ** -0.5, lam ** -0.5])
    expect = sum(m * np.sum(stretches ** a) for m, a in zip(fat.mu_MPa, fat.alpha,
                                                            strict=True)) / 3.0
    got = modulus(stretches)
    np.testing.assert_allclose(got, expect, rtol=1e-9)
    assert 15.0 * mu0 < got.min() < 30.0 * mu0


def test_kernel_reuses_the_residual_call_only_at_the_same_state():
    """Newton asks for the tangent where it has just evaluated the residual: the kernel reuses
    that call's stress and eigendecomposition, and the fields it writes are those of a fresh
    computation - also after the state or the parameters change."""
    k, u, mu, alpha = _cube_kernel(SKIN, (2, 1, 1))
    n = len(SKIN.mu_MPa)
    ncell = len(k.cells)

    def fresh():
        F = k._deformation_gradient()
        m = mu.x.array.reshape(-1, n)[k._blk]
        a = alpha.x.array.reshape(-1, n)[k._blk]
        P, A = ogden_dev_stress_tangent(F, m, a)
        return P.reshape(ncell, 9), A.reshape(ncell, 81)

    def fields():
        return (k.P.x.array.reshape(-1, 9)[k._pdof].copy(),
                k.A.x.array.reshape(-1, 81)[k._adof].copy())

    for shear in (0.2, -0.3):
        u.interpolate(lambda x, s=shear: np.vstack([s * x[1], 0.1 * x[0] * x[2], -s * x[2]]))
        k.update(tangent=False)
        P0, _ = fresh()
        np.testing.assert_array_equal(fields()[0], P0)
        k.update(tangent=True)  # same state: the tangent from the cached decomposition
        P, A = fields()
        P1, A1 = fresh()
        np.testing.assert_array_equal(P, P1)
        np.testing.assert_allclose(A, A1, rtol=0, atol=1e-15)
    mu.x.array[:] *= 2.0
    k.refresh_parameters()
    k.update(tangent=True)
    P, A = fields()
    P2, A2 = fresh()
    np.testing.assert_allclose(P, P2, rtol=1e-14, atol=0)
    np.testing.assert_allclose(A, A2, rtol=1e-14, atol=1e-15)
    assert np.abs(P2).max() > 0.0

"""Deviatoric Ogden stress and tangent per cell in NumPy, for linear tetrahedra.

The UFL form of the isochoric Ogden energy (eigenvalues of C by Cardano, a Taylor branch near
isotropy, :func:`handfe.materials._ufl_sum_powers`) differentiates twice into a kernel of ~60,000
lines: on the coarse pinch (23k tets) the tissue Jacobian took 2.7 s and the residual 0.8 s per
Newton iteration against 0.5-0.8 s for the MUMPS factorisation (1 rank, measured 1 Dec 2026).
With P1 displacements grad u is constant in a cell, so the first Piola stress and the tangent
dP/dF can be computed once per cell from the spectral decomposition of C (``numpy.linalg.eigh``)
and assembled as DG0 coefficients: ``int P : grad v`` and ``int grad v : A : grad du``.

Energy (as :class:`handfe.materials.Ogden`): W = sum_p 2 mu_p / alpha_p^2 (sum_a lb_a^alpha_p - 3),
lb_a = J^(-1/3) lambda_a. Units: MPa. Spectral formulas: Holzapfel, Nonlinear Solid Mechanics
(2000), eqs. 6.79 and 6.196-6.197 (the coincident-eigenvalue limit)."""

from __future__ import annotations

import numpy as np

#: relative gap |c_a - c_b| / c below which the coincident-eigenvalue limit is used
COINCIDENT_RTOL = 1e-6


def ogden_dev_stress_tangent(F: np.ndarray, mu: np.ndarray, alpha: np.ndarray, *,
                             tangent: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """First Piola stress P = dW/dF (n, 3, 3) and tangent A = d2W/dF dF (n, 3, 3, 3, 3), MPa,
    of the isochoric Ogden energy for deformation gradients ``F`` (n, 3, 3) with per-cell
    parameters ``mu``, ``alpha`` (n, m). ``A[:, i, J, k, L] = dP_iJ / dF_kL``; None unless
    ``tangent``."""
    with np.errstate(invalid="ignore", divide="ignore"):
        # an inverted cell (J <= 0, a Newton trial step) gives NaN, as the UFL kernel did:
        # the line search or the step cut handles it
        sp = _spectral(F, mu, alpha)
        return sp["P"], (_tangent(F, sp) if tangent else None)


# the unordered pairs (a, b), a < b, of principal directions
_PA, _PB = np.array([0, 0, 1]), np.array([1, 2, 2])


def _det3(F: np.ndarray) -> np.ndarray:
    """det F of (n, 3, 3), signed (10x cheaper than ``numpy.linalg.det``'s LU per matrix)."""
    return (F[:, 0, 0] * (F[:, 1, 1] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 1])
            - F[:, 0, 1] * (F[:, 1, 0] * F[:, 2, 2] - F[:, 1, 2] * F[:, 2, 0])
            + F[:, 0, 2] * (F[:, 1, 0] * F[:, 2, 1] - F[:, 1, 1] * F[:, 2, 0]))


def _spectral(F, mu, alpha) -> dict[str, np.ndarray]:
    """The stress P and the spectral quantities :func:`_tangent` needs. (Batched ``matmul``
    rather than ``einsum``: 2-6x faster on stacks of 3 x 3 matrices.)"""
    C = np.matmul(F.transpose(0, 2, 1), F)
    c, N = np.linalg.eigh(C)  # c ascending (n, 3); N[:, :, a] eigenvector a
    J = _det3(F)
    lb = np.sqrt(c) * (J ** (-1.0 / 3.0))[:, None]  # (n, 3) isochoric stretches
    # w_a = lb_a dW/dlb_a, h_a = lb_a d(w_a)/dlb_a
    pw = lb[:, :, None] ** alpha[:, None, :]  # (n, 3, m)
    w = np.einsum("nap,np->na", pw, 2.0 * mu / alpha)
    h = np.einsum("nap,np->na", pw, 2.0 * mu)
    beta = w - w.mean(axis=1, keepdims=True)  # principal Kirchhoff stress (deviatoric)
    S_a = beta / c
    S = np.matmul(N * S_a[:, None, :], N.transpose(0, 2, 1))  # sum_a S_a N_a x N_a
    P = np.matmul(F, S)
    return {"P": P, "c": c, "N": N, "h": h, "beta": beta, "S_a": S_a, "S": S}


def _tangent(F, sp: dict[str, np.ndarray]) -> np.ndarray:
    """The tangent A = dP/dF (n, 3, 3, 3, 3), MPa, from :func:`_spectral`'s data at ``F``."""
    n = F.shape[0]
    c, N, h, beta, S_a, S = (sp[k] for k in ("c", "N", "h", "beta", "S_a", "S"))
    # g_ab = lambda_b d(beta_a)/d(lambda_b)
    eye = np.eye(3)
    g = h[:, :, None] * eye - (h[:, :, None] + h[:, None, :]) / 3.0 \
        + h.sum(axis=1)[:, None, None] / 9.0
    # D_ab = (1/lambda_b) dS_a/dlambda_b
    D = (g - 2.0 * beta[:, :, None] * eye) / (c[:, :, None] * c[:, None, :])
    # per pair a < b: theta_ab = (S_b - S_a) / (c_b - c_a), coincident limit (D_bb - D_ab) / 2
    dc = c[:, _PB] - c[:, _PA]
    lim = 0.5 * (D[:, _PB, _PB] - D[:, _PA, _PB])
    close = np.abs(dc) <= COINCIDENT_RTOL * c.max(axis=1)[:, None]
    theta = np.where(close, lim, (S_a[:, _PB] - S_a[:, _PA]) / np.where(close, 1.0, dc))
    # A_iJkL = delta_ik S_JL + F_iI CC_IJKL F_kK with CC = 2 dS/dC; in the principal frame
    # CC_aabb = D_ab, CC_abab = CC_abba = theta_ab (a != b), and with Q_ab = (F N_a) x N_b the
    # second part is sum_ab D_ab Q_aa x Q_bb + sum_(a<b) theta_ab M_ab x M_ab, M_ab = Q_ab + Q_ba
    # (theta is symmetric): G^T K G with G = [Q_00, Q_11, Q_22, M_01, M_02, M_12] (n, 6, 9)
    # and K = diag(D, theta)
    ft = np.matmul(F, N).transpose(0, 2, 1)  # ft[n, a, i] = (F N_a)_i
    Nt = N.transpose(0, 2, 1)  # Nt[n, a, J] = (N_a)_J
    G = np.empty((n, 6, 3, 3))
    np.multiply(ft[:, :, :, None], Nt[:, :, None, :], out=G[:, :3])
    G[:, 3:] = ft[:, _PA, :, None] * Nt[:, _PB, None, :]
    G[:, 3:] += ft[:, _PB, :, None] * Nt[:, _PA, None, :]
    G = G.reshape(n, 6, 9)
    K = np.zeros((n, 6, 6))
    K[:, :3, :3] = D
    K[:, [3, 4, 5], [3, 4, 5]] = theta
    A9 = np.matmul(G.transpose(0, 2, 1), np.matmul(K, G))
    A = A9.reshape(n, 3, 3, 3, 3)
    for i in range(3):
        A[:, i, :, i, :] += S
    return A


class OgdenP1Kernel:
    """Per-cell deviatoric Ogden stress and tangent of a P1 displacement as DG0 fields.

    ``u``: the displacement (UFL expression of a P1 Function, e.g. ``ufl.split(w)[0]``);
    ``mu``, ``alpha``: DG0 vector Functions of the Ogden parameters (one block per cell).
    Call :meth:`update` whenever the state changes, before assembling :attr:`residual` or
    :attr:`jacobian` (forms in the test function ``v`` and trial function ``du`` given)."""

    def __init__(self, mesh, u, mu, alpha, v, du, dx):
        import ufl
        from dolfinx import fem

        self.mesh = mesh
        tdim = mesh.topology.dim
        im = mesh.topology.index_map(tdim)
        self.cells = np.arange(im.size_local + im.num_ghosts, dtype=np.int32)
        pts = np.array([[0.25, 0.25, 0.25]])  # one point: grad u is constant on a P1 tet
        self._grad = fem.Expression(ufl.grad(u), pts)
        self.P = fem.Function(fem.VectorFunctionSpace(mesh, ("DG", 0), dim=9), name="P_dev")
        self.A = fem.Function(fem.VectorFunctionSpace(mesh, ("DG", 0), dim=81), name="A_dev")
        self._pdof = self.P.function_space.dofmap.list.array[self.cells]
        self._adof = self.A.function_space.dofmap.list.array[self.cells]
        m = mu.function_space.num_sub_spaces
        blk = mu.function_space.dofmap.list.array[self.cells]
        self._mu = mu.x.array.reshape(-1, m)[blk]
        self._alpha = alpha.x.array.reshape(-1, m)[blk]
        self._mu_fn, self._alpha_fn, self._blk, self._m = mu, alpha, blk, m
        # [F, spectral data, tangent written] of the last update (see :meth:`update`)
        self._last: list | None = None
        Pm = ufl.as_matrix([[self.P[3 * i + j] for j in range(3)] for i in range(3)])
        Am = ufl.as_matrix([[self.A[9 * r + s] for s in range(9)] for r in range(9)])
        gv = ufl.grad(v)
        gd = ufl.grad(du)
        gv9 = ufl.as_vector([gv[i, j] for i in range(3) for j in range(3)])
        gd9 = ufl.as_vector([gd[i, j] for i in range(3) for j in range(3)])
        self.residual = ufl.inner(Pm, gv) * dx
        self.jacobian = ufl.dot(gv9, Am * gd9) * dx

    def forget(self, *, keep_stress: bool = False) -> None:
        """Make the next :meth:`update` recompute the tangent, and the stress too unless
        ``keep_stress`` (benchmarks time the computation this way)."""
        if keep_stress and self._last is not None:
            self._last[2] = False
        else:
            self._last = None

    def refresh_parameters(self) -> None:
        """Re-read the Ogden parameter Functions (after a material change)."""
        self.forget()
        self._mu = self._mu_fn.x.array.reshape(-1, self._m)[self._blk]
        self._alpha = self._alpha_fn.x.array.reshape(-1, self._m)[self._blk]

    def _deformation_gradient(self) -> np.ndarray:
        """F of each cell (local and ghost), (n, 3, 3): constant on a P1 tet."""
        return self._grad.eval(self.cells).reshape(-1, 3, 3) + np.eye(3)

    def shear_modulus(self) -> np.ndarray:
        """Incremental shear modulus of each cell (local and ghost, MPa) at the current state,
        averaged over the principal planes: (1/3) sum_i sum_p mu_p lbar_i^alpha_p (lbar the
        isochoric principal stretches). It is the exact modulus mu_p lbar^alpha_p of the
        Ogden (Abaqus-form) terms where the stretches coincide, sum mu_p = mu0 at rest, and
        grows with the stiffening: ~20 x mu0 for subcutaneous fat at 50 % uniaxial
        compression. Clipped below at mu0."""
        F = self._deformation_gradient()
        C = np.einsum("cki,ckj->cij", F, F)
        lam2 = np.clip(np.linalg.eigvalsh(C), 1e-12, None)
        J = np.sqrt(np.prod(lam2, axis=1))
        lbar = np.sqrt(lam2) / np.cbrt(J)[:, None]
        mu, al = self._mu, self._alpha
        mt = np.einsum("cp,cip->c", mu, lbar[:, :, None] ** al[:, None, :]) / 3.0
        return np.maximum(mt, mu.sum(axis=1))

    def update(self, tangent: bool = True) -> None:
        """Stress (and the tangent if ``tangent``) from the current displacement, on ghost
        cells too (no scatter needed). Newton asks for the tangent where it has just evaluated
        the residual: the same F reuses that call's eigendecomposition and stress (the
        residual's share was half the tangent call's 50 ms per rank on the coarse pinch)."""
        F = self._deformation_gradient()
        last = self._last
        with np.errstate(invalid="ignore", divide="ignore"):  # as ogden_dev_stress_tangent
            if last is None or not np.array_equal(F, last[0]):
                sp = _spectral(F, self._mu, self._alpha)
                self.P.x.array.reshape(-1, 9)[self._pdof] = sp["P"].reshape(-1, 9)
                last = self._last = [F, sp, False]
            if tangent and not last[2]:
                A = _tangent(F, last[1])
                self.A.x.array.reshape(-1, 81)[self._adof] = A.reshape(-1, 81)
                last[2] = True

"""Contact outputs (handfe.contact.contact_metrics) against analytical values on a unit box.

The top face z = 1 of a unit cube (6x6x6 tets) is deformed by the affine displacement
u = (a X, b Y, s (X - 1/2)) and touched by a rigid plate filling z > 1 + c (obstacle normal -z).
Deformed top: ((1+a) X, (1+b) Y, 1 + s (X - 1/2)); gap = c - s (X - 1/2); the patch within
gap_tol is the strip X >= X0 = 1/2 + (c - tol)/s, exactly resolved by the facet clipping
although X0 is not a mesh line."""

import numpy as np
import pytest
from mpi4py import MPI

from handfe.contact import HalfSpace, contact_metrics, ufl_contact_terms
from handfe.errors import InputError

A, B, S = 0.1, 0.05, 0.2
C = S / 6.0  # pressure kink at X1 = 2/3, a mesh line: force integrals are exact
TOL = 0.01
K = 2.0  # penalty, N/mm^3


def _setup(comm):
    import ufl
    from dolfinx import fem, mesh

    msh = mesh.create_unit_cube(comm, 6, 6, 6)
    fdim = 2
    top = mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[2], 1.0))
    ft = mesh.meshtags(msh, fdim, np.sort(top).astype(np.int32),
                       np.full(len(top), 7, dtype=np.int32))
    V = fem.VectorFunctionSpace(msh, ("CG", 1))
    u = fem.Function(V)
    u.interpolate(lambda x: np.vstack([A * x[0], B * x[1], S * (x[0] - 0.5)]))
    plate = HalfSpace(point=(0.0, 0.0, 1.0), normal=(0.0, 0.0, -1.0))
    tr = fem.Constant(msh, np.array([0.0, 0.0, C]))
    X = ufl.SpatialCoordinate(msh)
    g, _ = plate.ufl_gap_normal(X + u, tr)
    p = K * ufl.max_value(-g, 0.0)
    return msh, ft, u, plate, tr, p


def _analytic():
    x0 = 0.5 + (C - TOL) / S
    x1 = 0.5 + C / S
    jac = (1 + B) * np.hypot(1 + A, S)  # deformed area per reference area of the top face
    area = (1 - x0) * jac
    psum = K * S * (1 - x1) ** 2 / 2 * jac  # int p da, MPa mm^2 = N
    return {
        "area": area,
        "length": (1 + A) * (1 - x0),
        "width": 1 + B,
        "centroid": ((1 + A) * (1 + x0) / 2, (1 + B) / 2, 1 + S * ((1 + x0) / 2 - 0.5)),
        "pen": S * 0.5 - C,
        "force": psum,
        "mean_kPa": 1e3 * psum / area,
        "peak_kPa": 1e3 * K * (S * 0.5 - C),
    }


def _check(m, ref):
    assert m.contact_area_mm2 == pytest.approx(ref["area"], rel=1e-12)
    assert m.length_mm == pytest.approx(ref["length"], rel=1e-12)
    assert m.width_mm == pytest.approx(ref["width"], rel=1e-12)
    np.testing.assert_allclose(m.centroid_mm, ref["centroid"], rtol=1e-12)
    assert m.max_penetration_mm == pytest.approx(ref["pen"], rel=1e-12)
    assert m.min_gap_mm == pytest.approx(-ref["pen"], rel=1e-12)
    assert m.normal_force_N == pytest.approx(ref["force"], rel=1e-10)
    np.testing.assert_allclose(m.force_vector_N, [0.0, 0.0, -ref["force"]], atol=1e-12)
    assert m.mean_pressure_kPa == pytest.approx(ref["mean_kPa"], rel=1e-10)
    assert m.peak_pressure_kPa == pytest.approx(ref["peak_kPa"], rel=1e-12)


def _metrics(comm, **kw):
    """Metrics of the box; the clipped area (exact here) unless ``area`` is given."""
    msh, ft, u, plate, tr, p = _setup(comm)
    kw.setdefault("area", "clip")
    return contact_metrics(u, plate, (0.0, 0.0, C), ft, 7, gap_tol_mm=TOL, pressure=p,
                           comm=comm, **kw)


def test_metrics_plate_analytic_serial():
    m = _metrics(MPI.COMM_SELF)
    _check(m, _analytic())
    assert m.tangential_force_N == 0.0


@pytest.mark.mpi
def test_metrics_plate_analytic_mpi():
    """Same numbers on MPI.COMM_WORLD (2 ranks under make test-mpi) as on one rank."""
    comm = MPI.COMM_WORLD
    m = _metrics(comm)
    _check(m, _analytic())
    m1 = _metrics(MPI.COMM_SELF)
    for k, v in m.as_dict().items():
        np.testing.assert_allclose(v, m1.as_dict()[k], rtol=1e-12, atol=1e-14)
    # every rank holds the reduced result
    assert comm.allreduce(m.contact_area_mm2, op=MPI.MAX) == comm.allreduce(
        m.contact_area_mm2, op=MPI.MIN)
    mn, mn1 = _metrics(comm, area="nodal"), _metrics(MPI.COMM_SELF, area="nodal")
    for k, v in mn.as_dict().items():
        np.testing.assert_allclose(v, mn1.as_dict()[k], rtol=1e-12, atol=1e-14)


def test_metrics_of_a_half_model_are_the_whole_bodys():
    """symmetry_normal = y: the box is the half Y >= 0 of the body -1 <= Y <= 1 (u_y = B Y is
    odd, the rest even in Y): area, force and the extent across the plane double, the centroid
    moves onto the plane, length, pressures and penetration stay."""
    ref = _analytic()
    m = _metrics(MPI.COMM_SELF, symmetry_normal=(0.0, 1.0, 0.0))
    assert m.contact_area_mm2 == pytest.approx(2 * ref["area"], rel=1e-12)
    assert m.length_mm == pytest.approx(ref["length"], rel=1e-12)
    assert m.width_mm == pytest.approx(2 * ref["width"], rel=1e-12)
    cx, _, cz = ref["centroid"]
    np.testing.assert_allclose(m.centroid_mm, (cx, 0.0, cz), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(m.force_vector_N, [0.0, 0.0, -2 * ref["force"]], atol=1e-12)
    assert m.normal_force_N == pytest.approx(2 * ref["force"], rel=1e-10)
    assert m.mean_pressure_kPa == pytest.approx(ref["mean_kPa"], rel=1e-10)
    assert m.peak_pressure_kPa == pytest.approx(ref["peak_kPa"], rel=1e-12)
    assert m.max_penetration_mm == pytest.approx(ref["pen"], rel=1e-12)
    with pytest.raises(InputError, match="symmetry plane"):
        _metrics(MPI.COMM_SELF, symmetry_normal=(0.0, 1.0, 0.0),
                 axes=((1.0, 1.0, 0.0), (0.0, 0.0, 1.0)))


def test_area_continuous_in_plate_position():
    """Moving the plate by dc changes the area by at most dA = width * jac * dc / s: no jump
    when a node enters the patch, and no pressure needed for the geometric outputs."""
    msh, ft, u, plate, _, _ = _setup(MPI.COMM_SELF)
    jac = (1 + B) * np.hypot(1 + A, S)
    cs = np.linspace(0.0, 0.1, 41)
    areas = np.array([contact_metrics(u, plate, (0, 0, c), ft, 7, comm=MPI.COMM_SELF,
                                      area="clip").contact_area_mm2 for c in cs])
    dA = np.diff(areas)
    assert np.all(dA <= 1e-12)  # plate retracting: area shrinks monotonically
    assert np.all(np.abs(dA) <= jac * (cs[1] - cs[0]) / S * (1 + 1e-9))
    m = contact_metrics(u, plate, (0, 0, 0.5), ft, 7, comm=MPI.COMM_SELF)
    assert m.contact_area_mm2 == 0.0 and np.isnan(m.normal_force_N)
    assert m.min_gap_mm == pytest.approx(0.5 - 0.1, rel=1e-12)  # plate at 1.5, top at most 1.1
    assert m.length_mm == 0.0 and np.all(np.isnan(m.centroid_mm))


def _kinked_patch_areas(x0: float, k: float = 0.1, n: int = 6,
                        L: float = 12.0) -> tuple[float, float, float]:
    """A patch edge as in a real contact: the top face z = 1 of an L x L x 1 mm box (n x n x 2
    cells, P2 u) lies flat on the plate for X >= x0 and leaves it as gap = k (x0 - X)^(3/2)
    for X < x0 (the kink at the edge; k = 0.1 mm^-1/2 gives ~0.1 mm = 10 TOL one
    sub-element out, slopes <= 0.15 near the edge: the fingertip's proportions at 1 mm pad
    size). Returns (exact area of gap <= TOL, nodal area, clipped area), mm^2."""
    from dolfinx import fem, mesh

    msh = mesh.create_box(MPI.COMM_SELF, [np.zeros(3), np.array([L, L, 1.0])], [n, n, 2])
    top = mesh.locate_entities_boundary(msh, 2, lambda x: np.isclose(x[2], 1.0))
    ft = mesh.meshtags(msh, 2, np.sort(top).astype(np.int32), np.full(len(top), 7, np.int32))
    u = fem.Function(fem.VectorFunctionSpace(msh, ("CG", 2)))
    u.interpolate(lambda x: np.vstack([0 * x[0], 0 * x[0],
                                       -k * np.maximum(x0 - x[0], 0.0) ** 1.5 * x[2]]))
    plate = HalfSpace(point=(0.0, 0.0, 1.0), normal=(0.0, 0.0, -1.0))
    xe = x0 - (TOL / k) ** (2.0 / 3.0)
    # deformed area of X >= xe: the flat part plus the gently sloped band
    s = np.linspace(xe, x0, 2001)
    slope = 1.5 * k * np.sqrt(np.maximum(x0 - s, 0.0))
    f = np.sqrt(1.0 + slope**2)
    exact = L * ((L - x0) + float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(s))))
    a = {m: contact_metrics(u, plate, (0, 0, 0), ft, 7, gap_tol_mm=TOL, comm=MPI.COMM_SELF,
                            area=m).contact_area_mm2 for m in ("nodal", "clip")}
    return exact, a["nodal"], a["clip"]


def test_nodal_area_unbiased_at_a_kinked_patch_edge():
    """Why the nodal area is the default (module docstring of handfe.contact): with the edge
    swept across one sub-element (the facets split at their edge midpoints, 1 mm here), the
    linearly interpolated (clipped) area is short at every position, by a quarter of a
    sub-element strip on average (measured -0.255 mm); the nodal area is right on average
    (+0.036 mm) and never off by more than half a strip (0.497 mm)."""
    hs, L = 1.0, 12.0
    rows = np.array([_kinked_patch_areas(x0) for x0 in 6.0 + hs * (np.arange(12) + 0.5) / 12])
    err_nodal, err_clip = (rows[:, 1:] - rows[:, :1]).T / L  # as a strip width, mm
    assert np.all(err_clip < 0) and np.mean(err_clip) < -0.2 * hs
    assert abs(np.mean(err_nodal)) < 0.2 * abs(np.mean(err_clip))
    assert np.max(np.abs(err_nodal)) <= 0.5 * hs + 1e-9


def test_contact_terms_consistent_with_metrics():
    """The residual of ufl_contact_terms is -int p n . v da: summed over the z dofs it equals
    -F_z reported by contact_metrics; frictional terms: stick below mu p, slip limit above."""
    import ufl
    from dolfinx import fem

    msh, ft, u, plate, tr, _ = _setup(MPI.COMM_SELF)
    V = u.function_space
    v = ufl.TestFunction(V)
    ds = ufl.Measure("ds", domain=msh, subdomain_data=ft, metadata={"quadrature_degree": 2})
    kn = fem.Constant(msh, K)
    lam = fem.Function(fem.FunctionSpace(msh, ("CG", 1)))
    terms = ufl_contact_terms(u, v, plate, tr, ds(7), k_n=kn, lambda_n=lam)
    R = fem.petsc.assemble_vector(fem.form(terms.residual))
    Rz = R.array.reshape(-1, 3)[:, 2].sum()
    m = contact_metrics(u, plate, (0.0, 0.0, C), ft, 7, pressure=terms.pressure,
                        comm=MPI.COMM_SELF)
    assert Rz == pytest.approx(-m.force_vector_N[2], rel=1e-10)
    assert m.normal_force_N == pytest.approx(_analytic()["force"], rel=1e-10)

    # friction: anchor u_ref = u - slip (tangential, along x), obstacle not moved
    mu = fem.Constant(msh, 0.5)
    kt = fem.Constant(msh, 10.0)
    u_ref = fem.Function(V)
    tr_ref = fem.Constant(msh, np.array([0.0, 0.0, C]))
    fterms = ufl_contact_terms(u, v, plate, tr, ds(7), k_n=kn, mu=mu, k_t=kt, u_ref=u_ref,
                               translation_ref=tr_ref)
    for slip, stick in ((1e-5, True), (1e-1, False)):
        u_ref.interpolate(lambda x, s=slip: np.vstack([A * x[0] - s, B * x[1],
                                                       S * (x[0] - 0.5)]))
        mt = contact_metrics(u, plate, (0.0, 0.0, C), ft, 7, pressure=fterms.pressure,
                             tangential_traction=fterms.tangential_traction,
                             comm=MPI.COMM_SELF)
        # tangential slip s = P_T (slip e_x): traction -k_t s (stick) or -mu p s/|s| (slip)
        if stick:
            # stick wherever p > k_t |s| / mu: all of X > 2/3 but a rim of width 5e-5
            assert mt.tangential_force_N == pytest.approx(10.0 * slip * _tan_area(), rel=2e-3)
        else:
            assert mt.tangential_force_N == pytest.approx(0.5 * mt.normal_force_N, rel=1e-9)


def _tan_area():
    """Deformed area of the region where p > 0 (X >= 2/3)."""
    return (1 - 2 / 3) * (1 + B) * np.hypot(1 + A, S)


def test_uzawa_update():
    """lambda_n <- max(0, lambda_n - k g) at the dofs of the contact facets; reports the
    largest change and penetration."""
    import ufl
    from dolfinx import fem

    from handfe.contact import UzawaUpdate

    msh, ft, u, plate, tr, _ = _setup(MPI.COMM_SELF)
    v = ufl.TestFunction(u.function_space)
    ds = ufl.Measure("ds", domain=msh, subdomain_data=ft)
    lam = fem.Function(fem.FunctionSpace(msh, ("CG", 1)))
    terms = ufl_contact_terms(u, v, plate, tr, ds(7), k_n=fem.Constant(msh, K), lambda_n=lam)
    update = UzawaUpdate(terms, ft.find(7))
    change, pen = update()
    assert pen == pytest.approx(S * 0.5 - C, rel=1e-12)
    assert change == pytest.approx(K * (S * 0.5 - C), rel=1e-12)
    x = lam.function_space.tabulate_dof_coordinates()
    expect = np.where(np.isclose(x[:, 2], 1.0), K * np.maximum(S * (x[:, 0] - 0.5) - C, 0), 0)
    np.testing.assert_allclose(lam.x.array, expect, atol=1e-14)
    change2, _ = update()  # second update: lambda grows by k * penetration again
    assert change2 == pytest.approx(K * (S * 0.5 - C), rel=1e-12)


def test_contact_jacobian_matches_finite_differences():
    """ufl.derivative of the residual (normal + friction, Nanson factor) is finite and
    equals the central finite difference of the residual in a random direction."""
    import ufl
    from dolfinx import fem
    from dolfinx.fem.petsc import assemble_matrix, assemble_vector

    msh, ft, u, plate, tr, _ = _setup(MPI.COMM_SELF)
    V = u.function_space
    v = ufl.TestFunction(V)
    ds = ufl.Measure("ds", domain=msh, subdomain_data=ft, metadata={"quadrature_degree": 2})
    u_ref = fem.Function(V)
    u_ref.interpolate(lambda x: np.vstack([A * x[0] - 2e-3 * x[1], B * x[1], S * (x[0] - 0.5)]))
    lam = fem.Function(fem.FunctionSpace(msh, ("CG", 1)))
    lam.x.array[:] = 0.01
    terms = ufl_contact_terms(u, v, plate, tr, ds(7), k_n=fem.Constant(msh, K), lambda_n=lam,
                              mu=fem.Constant(msh, 0.74), k_t=fem.Constant(msh, 1.0),
                              u_ref=u_ref, translation_ref=fem.Constant(msh, np.zeros(3)))
    F = fem.form(terms.residual)
    J = assemble_matrix(fem.form(ufl.derivative(terms.residual, u)))
    J.assemble()
    assert np.isfinite(J.norm())
    du = J.createVecRight()
    du.array[:] = np.random.default_rng(3).uniform(-1, 1, du.array.shape)
    Jdu = J.createVecLeft()
    J.mult(du, Jdu)
    u0 = u.x.array.copy()
    eps = 1e-7
    res = []
    for sgn in (1, -1):
        u.x.array[:] = u0 + sgn * eps * du.array
        res.append(assemble_vector(F).array.copy())
    u.x.array[:] = u0
    fd = (res[0] - res[1]) / (2 * eps)
    assert np.linalg.norm(fd - Jdu.array) <= 1e-5 * np.linalg.norm(Jdu.array)

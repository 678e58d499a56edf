"""Rigid obstacles: signed gap and normal in NumPy and UFL (handfe.contact)."""

import numpy as np
import pytest

from handfe.contact import (
    Capsule,
    Cylinder,
    HalfSpace,
    RoundedBox,
    Sphere,
    Union,
    penalty_stiffness,
    plate,
    rotation_matrix,
)
from handfe.errors import InputError

OBSTACLES = {
    "halfspace": HalfSpace(point=(0.1, -0.2, 0.3), normal=(0.3, -0.5, 1.0)),
    "sphere": Sphere(centre=(0.2, 0.0, -0.1), radius=1.3),
    "capsule": Capsule(p0=(-1.0, -0.5, 0.0), p1=(1.2, 0.4, 0.3), radius=0.7),
    "cylinder_sharp": Cylinder(centre=(0.0, 0.1, 0.0), axis=(0.2, 1.0, 0.1), radius=1.1,
                               half_length=1.4),
    "cylinder_round": Cylinder(centre=(0.0, 0.0, 0.2), axis=(1.0, 0.0, 0.3), radius=1.2,
                               half_length=1.0, edge_radius=0.4),
    "box": RoundedBox(centre=(0.1, 0.0, 0.0), half_sizes=(1.5, 0.8, 1.0),
                      rotation=rotation_matrix((1.0, 2.0, 0.5), 30.0), edge_radius=0.3),
    "box_sharp": RoundedBox(centre=(0.0, 0.0, 0.0), half_sizes=(1.0, 1.2, 0.7)),
}
OBSTACLES["union"] = Union((OBSTACLES["sphere"], OBSTACLES["box"],
                            Cylinder(centre=(-1.5, 1.0, 0.0), radius=0.6, half_length=0.8,
                                     edge_radius=0.2)))
CONVEX = [k for k in OBSTACLES if k != "union"]


def _points(n=3000, seed=1):
    return np.random.default_rng(seed).uniform(-2.5, 2.5, size=(n, 3))


@pytest.mark.parametrize("name", list(OBSTACLES))
def test_normal_unit_and_gap_lipschitz(name):
    ob = OBSTACLES[name]
    x = _points()
    g, n = ob.gap_normal(x)
    assert g.shape == (len(x),) and n.shape == (len(x), 3)
    assert np.all(np.isfinite(g)) and np.all(np.isfinite(n))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert (g < 0).any() and (g > 0).any()  # the sample covers inside and outside
    y = _points(seed=2)
    gy, _ = ob.gap_normal(y)
    assert np.all(np.abs(g - gy) <= np.linalg.norm(x - y, axis=1) * (1 + 1e-12) + 1e-12)


@pytest.mark.parametrize("name", list(OBSTACLES))
def test_normal_is_gradient_of_gap(name):
    ob = OBSTACLES[name]
    x = _points(1500, seed=3)
    g, n = ob.gap_normal(x)
    h = 1e-6
    fd = np.stack([(ob.gap_normal(x + h * e)[0] - ob.gap_normal(x - h * e)[0]) / (2 * h)
                   for e in np.eye(3)], axis=1)
    err = np.linalg.norm(fd - n, axis=1)
    if name in CONVEX:
        # the signed distance of a convex set is C1 outside it: agreement everywhere
        out = g > 1e-3
        assert err[out].max() < 1e-6
    else:
        out = np.ones(len(x), bool)
    # inside, the gradient jumps on the medial set only (a null set): nearly all points agree
    assert np.mean(err < 1e-6) > 0.97
    assert np.mean(err[out] < 1e-6) > 0.97


def test_closest_point_is_on_surface():
    """x - g n is on the surface (gap 0) and has the same normal."""
    for name in CONVEX:
        ob = OBSTACLES[name]
        x = _points(500, seed=4)
        g, n = ob.gap_normal(x)
        xs = x - g[:, None] * n
        gs, ns = ob.gap_normal(xs)
        assert np.abs(gs).max() < 1e-9, name
        if name.endswith("_sharp"):
            continue  # points outside a sharp edge project onto the edge, normal undefined there
        ok = np.abs(g) > 1e-3
        assert np.mean(np.linalg.norm(ns - n, axis=1)[ok] < 1e-6) > 0.97, name


def test_known_values_and_translation():
    s = Sphere(centre=(1.0, 0.0, 0.0), radius=2.0)
    g, n = s.gap_normal(np.array([[4.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), translation=(0, 0, 1))
    assert g[0] == pytest.approx(np.sqrt(10.0) - 2.0)
    assert g[1] == pytest.approx(-1.0)
    np.testing.assert_allclose(n[1], [0, 0, -1], atol=1e-14)
    p = plate(90.0, point=(5.0, 0.0, 0.0))
    g, n = p.gap_normal(np.array([[3.0, 7.0, -1.0]]))
    assert g[0] == pytest.approx(2.0)
    np.testing.assert_allclose(n[0], [-1, 0, 0], atol=1e-15)
    # a cylinder with edge radius = radius is a capsule of the same length
    c = Cylinder(centre=(0, 0, 0), axis=(0, 0, 1), radius=1.0, half_length=2.0, edge_radius=1.0)
    k = Capsule(p0=(0, 0, -1.0), p1=(0, 0, 1.0), radius=1.0)
    x = _points(300, seed=5)
    np.testing.assert_allclose(c.gap_normal(x)[0], k.gap_normal(x)[0], atol=1e-12)
    b = RoundedBox(half_sizes=(1.0, 2.0, 3.0), edge_radius=0.5)
    assert b.gap_normal(np.array([[2.0, 3.0, 0.0]]))[0][0] == pytest.approx(np.sqrt(4.5) - 0.5)
    assert b.gap_normal(np.array([[0.0, 0.0, 0.0]]))[0][0] == pytest.approx(-1.0)


def test_bad_input():
    with pytest.raises(InputError, match="radius"):
        Sphere(radius=-1.0)
    with pytest.raises(InputError, match="normal"):
        HalfSpace(normal=(0, 0, 0))
    with pytest.raises(InputError, match="edge_radius"):
        Cylinder(radius=1.0, half_length=1.0, edge_radius=2.0)
    with pytest.raises(InputError, match="angle"):
        plate(120.0)
    with pytest.raises(InputError, match="h_mm"):
        penalty_stiffness(0.05, 0.0)
    assert penalty_stiffness(0.05, 0.5) == pytest.approx(1.0)


def test_ufl_equals_numpy():
    """All obstacles in one compiled Expression, x = X + u with a random P1 u, translation a
    Constant; evaluated at random reference points and at cell vertices (includes the sphere
    centre and axis points, where the guards act)."""
    import ufl
    from dolfinx import fem, mesh
    from mpi4py import MPI

    msh = mesh.create_box(MPI.COMM_SELF, [np.array([-2.5, -2.5, -2.5]), np.array([2.5, 2.5, 2.5])],
                          [5, 5, 5])
    V = fem.VectorFunctionSpace(msh, ("CG", 1))
    u = fem.Function(V)
    rng = np.random.default_rng(7)
    u.x.array[:] = rng.uniform(-0.2, 0.2, size=u.x.array.shape)
    t_val = np.array([0.1, -0.2, 0.15])
    tr = fem.Constant(msh, t_val)
    x = ufl.SpatialCoordinate(msh) + u
    comps = [x[i] for i in range(3)]
    for ob in OBSTACLES.values():
        g, n = ob.ufl_gap_normal(x, tr)
        comps += [g, n[0], n[1], n[2]]
    ref = np.vstack([np.eye(3), np.zeros((1, 3)), rng.dirichlet(np.ones(4), size=6)[:, :3]])
    expr = fem.Expression(ufl.as_vector(comps), ref)
    cells = np.arange(msh.topology.index_map(3).size_local, dtype=np.int32)
    vals = expr.eval(cells).reshape(len(cells), ref.shape[0], -1).reshape(-1, len(comps))
    assert np.all(np.isfinite(vals))
    xs = vals[:, :3]
    for k, ob in enumerate(OBSTACLES.values()):
        g, n = ob.gap_normal(xs, t_val)
        np.testing.assert_allclose(vals[:, 3 + 4 * k], g, atol=1e-12, rtol=0)
        np.testing.assert_allclose(vals[:, 4 + 4 * k: 7 + 4 * k], n, atol=1e-12, rtol=0)


def test_ufl_guard_at_singular_points():
    """Gap and normal finite at a sphere centre / on a capsule axis (the points hit exactly)."""
    s = Sphere(centre=(0.0, 0.0, 0.0), radius=1.0)
    g, n = s.gap_normal(np.zeros((1, 3)))
    assert g[0] == pytest.approx(-1.0) and np.linalg.norm(n[0]) == pytest.approx(1.0)
    c = Cylinder(axis=(0, 0, 1), radius=1.0, half_length=3.0, edge_radius=0.2)
    g, n = c.gap_normal(np.zeros((1, 3)))
    assert g[0] == pytest.approx(-1.0) and np.linalg.norm(n[0]) == pytest.approx(1.0)


def test_friction_anchor_update():
    """Stuck nodes keep their anchor; slipped nodes keep exactly the Coulomb limit."""
    from handfe.contact import friction_anchor_update

    s = np.array([[1e-4, 0, 0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.0]])
    p = np.array([0.1, 0.1, 0.0])
    shift = friction_anchor_update(s, p, mu=0.5, k_t=10.0)
    np.testing.assert_allclose(shift[0], 0.0, atol=1e-15)  # k_t |s| = 1e-3 <= mu p = 0.05
    left = s[1] - shift[1]
    assert 10.0 * np.linalg.norm(left) == pytest.approx(0.5 * 0.1)
    np.testing.assert_allclose(shift[2], 0.0, atol=1e-15)


def test_smoothed_cone_joins_stick_and_slip_with_a_continuous_slope():
    """The rounded Coulomb cone equals the sharp law outside (1 +- delta) mu p, never exceeds
    mu p, keeps the trial's direction, and its magnitude has no slope jump at the band's
    edges (the sharp law jumps from 1 to 0 at mu p)."""
    import ufl
    from dolfinx import fem, mesh
    from mpi4py import MPI
    from petsc4py import PETSc

    from handfe.contact import smoothed_cone

    m = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1)
    trial = fem.Constant(m, PETSc.ScalarType((0.0, 0.0, 0.0)))
    limit = fem.Constant(m, PETSc.ScalarType(0.2))  # mu p, MPa
    delta = fem.Constant(m, PETSc.ScalarType(0.1))
    e = np.array([0.6, -0.8, 0.0])
    tT = smoothed_cone(trial, limit, delta)
    along = fem.form(ufl.dot(tT, ufl.as_vector(e.tolist())) * ufl.dx)
    across = fem.form(ufl.dot(tT, ufl.as_vector([0.8, 0.6, 0.0])) * ufl.dx)

    def mag(t: float, d: float = 0.1) -> float:
        trial.value = t * e
        delta.value = d
        assert abs(fem.assemble_scalar(across)) < 1e-14
        return fem.assemble_scalar(along)

    L = 0.2
    for t in (0.0, 0.05, 0.17, 0.179, 0.221, 0.3, 2.0):  # outside the band: the sharp law
        assert mag(t) == pytest.approx(min(t, L), abs=1e-14)
        assert mag(t, 0.0) == pytest.approx(min(t, L), abs=1e-14)
    band = np.linspace(0.18, 0.22, 41)
    vals = np.array([mag(t) for t in band])
    assert np.all(vals <= L + 1e-15) and np.all(np.diff(vals) >= 0.0)
    assert mag(L) == pytest.approx(L * (1.0 - 0.1 / 4.0))  # the largest deviation, delta/4
    h = 1e-7
    for edge, slope in ((0.18, 1.0), (0.22, 0.0)):
        left = (mag(edge) - mag(edge - h)) / h
        right = (mag(edge + h) - mag(edge)) / h
        assert left == pytest.approx(slope, abs=1e-5) and right == pytest.approx(slope, abs=1e-5)
    trial.value = np.zeros(3)
    limit.value = 0.0  # out of contact: no traction, no NaN from the guarded blend
    assert fem.assemble_scalar(along) == 0.0

"""The FE solver core against closed forms: homogeneous cube (1e-6), consistent tangent
(finite differences), quadratic Newton from the reference state, step cutting and errors."""

import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from mpi4py import MPI
from petsc4py import PETSc

from handfe.errors import InputError, SolverError
from handfe.materials import (
    MODES,
    MooneyRivlin,
    NeoHookean,
    Ogden,
    StVenantKirchhoff,
    homogeneous,
)
from handfe.solver import (
    FAST_COMPILE,
    FAST_COMPILE_MAX_CELLS,
    Discretisation,
    HyperelasticProblem,
    LoadStepping,
    NewtonOptions,
    solve,
)
from handfe.verification import _facets, cube_stress_curve, unit_cube

LAMS = [0.7, 1.0, 1.3, 1.6]


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("mat,incompressible", [
    (Ogden.skin(), True), (Ogden.subcutaneous(), False), (MooneyRivlin.fingertip_mean(), True),
    (NeoHookean.from_E_nu(0.05, 0.45), False), (StVenantKirchhoff.from_E_nu(1.0, 0.3), False),
], ids=["ogden-skin-inc", "ogden-subcut", "mr-inc", "neo-hookean", "svk"])
def test_fe_cube_matches_closed_form(mat, incompressible, mode):
    lams = LAMS if mat.law != "st-venant-kirchhoff" else [0.9, 1.0, 1.2]
    fe = cube_stress_curve(mat, mode, lams, incompressible=incompressible, comm=MPI.COMM_SELF)
    cf = np.array([homogeneous(mat, mode, x, incompressible=incompressible)[0] for x in lams])
    scale = np.max(np.abs(cf))
    assert np.max(np.abs(fe - cf)) <= 1e-6 * scale


@pytest.mark.parametrize("mat", [Ogden.subcutaneous(nu=0.499), NeoHookean.from_E_nu(0.05, 0.45)],
                         ids=["ogden-subcut", "neo-hookean"])
def test_fe_cube_matches_closed_form_in_confined_compression(mat):
    # uniaxial strain (lambda, 1, 1): a tissue layer squeezed between a bone and an object
    lams = [0.2, 0.5, 0.9, 1.0, 1.2]
    fe = cube_stress_curve(mat, "confined", lams, comm=MPI.COMM_SELF)
    cf = np.array([homogeneous(mat, "confined", x)[0] for x in lams])
    assert np.max(np.abs(fe - cf)) <= 1e-6 * np.max(np.abs(cf))


def _cube_problem(mat, disc=None):
    msh = unit_cube(MPI.COMM_SELF, 2)
    prob = HyperelasticProblem(msh, mat, disc=disc or Discretisation())
    return msh, prob


def _assemble(prob):
    L, a = prob.compiled()
    b = fem_petsc.assemble_vector(L)
    b.ghostUpdate()
    A = fem_petsc.assemble_matrix(a)
    A.assemble()
    return b, A


@pytest.mark.parametrize("state", ["reference", "deformed"])
@pytest.mark.parametrize("mat", [Ogden.skin(), MooneyRivlin.fingertip_mean()],
                         ids=["ogden", "mooney-rivlin"])
def test_consistent_tangent_finite_differences(mat, state):
    """J dw == (R(w + h dw) - R(w - h dw)) / 2h, at F = I and at a generic state with three
    distinct principal stretches (no NaN/inf anywhere)."""
    msh, prob = _cube_problem(mat)
    rng = np.random.default_rng(1)
    w0 = np.zeros_like(prob.w.x.array)
    if state == "deformed":
        Vu, _ = prob.W.sub(0).collapse()
        u = fem.Function(Vu)
        u.interpolate(lambda x: np.vstack([0.3 * x[0] + 0.1 * x[1] ** 2, -0.15 * x[1] + 0.05 *
                                           x[0] * x[2], 0.08 * x[2] - 0.1 * x[0] * x[1]]))
        prob.w.x.array[:] = 0.0
        prob.w.sub(0).interpolate(u)
        p_dofs = prob.W.sub(1).collapse()[1]
        prob.w.x.array[p_dofs] = 1e-4
        w0 = prob.w.x.array.copy()
    b, A = _assemble(prob)
    R0 = b.array.copy()
    assert np.all(np.isfinite(R0)) and np.all(np.isfinite(A.getValues(range(10), range(10))))
    if state == "reference":
        assert np.max(np.abs(R0)) < 1e-13  # stress-free, no spurious residual
    dw = rng.standard_normal(w0.shape)
    h = 1e-6
    out = []
    for sgn in (1, -1):
        prob.w.x.array[:] = w0 + sgn * h * dw
        b2, _ = _assemble(prob)
        out.append(b2.array.copy())
    fd = (out[0] - out[1]) / (2 * h)
    x = A.createVecRight()
    x.array[:] = dw
    y = A.createVecLeft()
    A.mult(x, y)
    assert np.linalg.norm(y.array - fd) <= 1e-6 * np.linalg.norm(fd)


@pytest.mark.parametrize("mat", [Ogden.skin(), MooneyRivlin.fingertip_mean()],
                         ids=["ogden", "mooney-rivlin"])
def test_newton_quadratic_from_reference_state(mat):
    msh, prob = _cube_problem(mat)
    for a in range(3):
        prob.fix(_facets(msh, a, 0.0), components=(a,))
    c = prob.fix(_facets(msh, 0, 1.0), components=(0,))

    def set_load(t):
        c.value = 0.3 * t

    res = solve(prob, set_load, stepping=LoadStepping(initial=1.0))
    hist = res.residual_history[0]
    assert res.load_steps == 1 and res.newton_iterations[0] <= 5
    # quadratic: log r_{k+1} / log r_k -> 2 in the last steps (relative to the first residual)
    rel = np.array(hist) / hist[0]
    assert rel[-1] < 1e-14
    k = int(np.argmax(rel < 1e-3))
    assert np.log(rel[k + 1]) / np.log(rel[k]) > 1.8


def test_step_cutting_and_failure_report():
    """An impossible load (push the face through the opposite one: J <= 0) fails with an error
    that names the load step and the residual; accepted steps were reported before."""
    mat = NeoHookean.from_E_nu(1.0, 0.3)
    msh, prob = _cube_problem(mat, Discretisation("p1"))
    for a in range(3):
        prob.fix(_facets(msh, a, 0.0), components=(a,))
    c = prob.fix(_facets(msh, 0, 1.0), components=(0,))
    seen = []

    def set_load(t):
        c.value = -1.5 * t

    with pytest.raises(SolverError, match=r"load step \d+ .*did not converge.*residual") as ei:
        solve(prob, set_load, stepping=LoadStepping(initial=0.5, min_step=1 / 64),
              on_step=lambda t, r: seen.append(t))
    assert ei.value.load_step is not None and ei.value.load_step >= 1
    assert seen == sorted(seen)  # steps before the failure were accepted and reported


def test_step_growth_and_cuts_recorded():
    mat = MooneyRivlin.fingertip_mean()
    msh, prob = _cube_problem(mat)
    for a in range(3):
        prob.fix(_facets(msh, a, 0.0), components=(a,))
    c = prob.fix(_facets(msh, 0, 1.0), components=(0,))

    def set_load(t):
        c.value = -0.5 * t

    res = solve(prob, set_load, stepping=LoadStepping(initial=0.1))
    assert res.converged and res.load_factors[-1] == pytest.approx(1.0)
    steps = np.diff([0.0] + res.load_factors)
    assert steps.max() > 0.1  # grew after easy steps
    assert len(res.newton_iterations) == res.load_steps == len(res.residual_history)
    s = res.summary()
    assert s["dofs"] == prob.num_dofs() and s["wall_s"] > 0


def test_bad_discretisation_inputs():
    with pytest.raises(InputError, match="unknown element"):
        Discretisation("q9")
    msh = unit_cube(MPI.COMM_SELF, 1)
    with pytest.raises(InputError, match="incompressible"):
        HyperelasticProblem(msh, Ogden.skin(), disc=Discretisation("p2"), incompressible=True)
    with pytest.raises(InputError, match="stretch"):
        cube_stress_curve(Ogden.skin(), "uniaxial", [-0.5], comm=MPI.COMM_SELF)


def test_small_meshes_compile_at_O0_and_larger_ones_at_the_defaults():
    # the verification cubes' Ogden kernels compile in seconds at -O0 instead of minutes at -O2
    small = HyperelasticProblem(unit_cube(MPI.COMM_SELF, 2), Ogden.skin(),
                                disc=Discretisation("taylor-hood"))
    assert small.jit_params == FAST_COMPILE
    assert unit_cube(MPI.COMM_SELF, 4).topology.index_map(3).size_global > \
        FAST_COMPILE_MAX_CELLS
    large = HyperelasticProblem(unit_cube(MPI.COMM_SELF, 4), Ogden.skin())
    assert large.jit_params == {}
    chosen = HyperelasticProblem(unit_cube(MPI.COMM_SELF, 1), Ogden.skin(), jit_params={})
    assert chosen.jit_params == {}
    # the same numbers either way (a small kernel: an Ogden one at -O2 takes minutes)
    reactions = []
    for params in (None, {}):
        prob = HyperelasticProblem(unit_cube(MPI.COMM_SELF, 2), NeoHookean.from_E_nu(1.0, 0.45),
                                   disc=Discretisation("p2"), jit_params=params)
        prob.w.interpolate(lambda x: np.vstack([0.1 * x[0] ** 2, -0.04 * x[1], -0.04 * x[2]]))
        reactions.append(prob.reaction(_facets(prob.mesh, 0, 1.0)))
    assert np.abs(reactions[0]).max() > 1e-3
    np.testing.assert_allclose(reactions[0], reactions[1], rtol=1e-12, atol=1e-15)


def test_assign_material_does_not_recompile():
    msh, prob = _cube_problem(Ogden.skin())
    L, a = prob.compiled()
    prob.assign_material(Ogden.subcutaneous())
    assert prob.compiled() == (L, a)
    assert ufl is not None


# -- p1-p0: P1 displacement + DG0 pressure (hybrid linear tet) ------------------------------------
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("incompressible", [True, False], ids=["inc", "nu049"])
def test_p1p0_cube_matches_closed_form(mode, incompressible):
    """Homogeneous deformations lie in the P1 space: the hybrid linear tet reproduces the closed
    form exactly, also exactly incompressible (pure P1 cannot be used there)."""
    mat = MooneyRivlin.fingertip_mean()
    lams = [0.7, 1.0, 1.3]
    disc = Discretisation("p1-p0")
    assert disc.mixed and disc.degree == 1 and disc.qdeg == 2
    fe = cube_stress_curve(mat, mode, lams, incompressible=incompressible, disc=disc,
                           comm=MPI.COMM_SELF, n=2)
    cf = np.array([homogeneous(mat, mode, x, incompressible=incompressible)[0] for x in lams])
    assert np.max(np.abs(fe - cf)) <= 1e-6 * np.max(np.abs(cf))


def test_p1p0_near_incompressible_distorted_patch():
    """Patch test: a cube with distorted interior nodes, neo-Hookean nu = 0.4999, uniaxial
    stretch 1.2 on x = 1 with symmetry planes. The exact solution is homogeneous: the reaction is
    the closed form, J is 1 to the compressibility, and the DG0 pressure is uniform."""
    from dolfinx import mesh as dmesh

    mat = NeoHookean.from_E_nu(0.05, 0.4999)
    msh = dmesh.create_unit_cube(MPI.COMM_SELF, 3, 3, 3, dmesh.CellType.tetrahedron)
    x = msh.geometry.x
    inner = np.all((x > 1e-8) & (x < 1 - 1e-8), axis=1)
    rng = np.random.default_rng(3)
    x[inner] += rng.uniform(-0.08, 0.08, size=(inner.sum(), 3))
    prob = HyperelasticProblem(msh, mat, disc=Discretisation("p1-p0"))
    fdim = 2
    for a in range(3):
        prob.fix(dmesh.locate_entities_boundary(msh, fdim, lambda p, a=a: np.isclose(p[a], 0)),
                 components=(a,))
    right = dmesh.locate_entities_boundary(msh, fdim, lambda p: np.isclose(p[0], 1.0))
    c = prob.fix(right, components=(0,))

    def set_load(t):
        c.value = 0.2 * t

    res = solve(prob, set_load, stepping=LoadStepping(initial=0.5))
    assert res.converged
    P11 = prob.reaction(right)[0]
    cf = homogeneous(mat, "uniaxial", 1.2)[0]
    assert P11 == pytest.approx(cf, rel=1e-6)
    p_dofs = prob.W.sub(1).collapse()[1]
    p = prob.w.x.array[p_dofs]
    assert np.ptp(p) <= 1e-6 * np.max(np.abs(p))
    J = fem.form(ufl.det(prob.F) * ufl.dx)
    assert fem.assemble_scalar(J) == pytest.approx(1.0, abs=2e-3)


def test_lifting_skipped_only_where_it_adds_zero():
    """lift_unless_satisfied: an iterate off the Dirichlet values is lifted exactly as by
    apply_lifting; one that holds them is not lifted (apply_lifting would add exactly 0)."""
    from handfe.solver import lift_unless_satisfied

    mat = NeoHookean.from_E_nu(1.0, 0.3)
    msh, prob = _cube_problem(mat, Discretisation("p1"))
    for a in range(3):
        prob.fix(_facets(msh, a, 0.0), components=(a,))
    c = prob.fix(_facets(msh, 0, 1.0), components=(0,))
    c.value = 0.1
    L, a = prob.compiled()
    rng = np.random.default_rng(0)
    x = fem_petsc.create_vector(L)
    x.array[:] = 0.01 * rng.standard_normal(x.array.shape)
    for holds in (False, True):
        if holds:
            fem_petsc.set_bc(x, prob.bcs)  # the iterate takes the Dirichlet values
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        prob.w.x.array[:] = 0.0
        ref, got, work = (fem_petsc.create_vector(L) for _ in range(3))
        for v in (ref, got):
            fem_petsc.assemble_vector(v, L)
        fem_petsc.apply_lifting(ref, [a], bcs=[prob.bcs], x0=[x], scale=-1.0)
        lifted = lift_unless_satisfied(got, [a], prob.bcs, x, work)
        assert lifted is not holds
        for v in (ref, got):
            v.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        assert np.array_equal(ref.array, got.array)


def _traction_cube(guard: float, line_search: str, steps: int) -> float:
    """Unit cube, Neo-Hookean (E = 1 MPa, nu = 0.3, P1), symmetry planes fixed, nominal
    compressive traction 1.5 MPa on x = 1; returns the smallest u_x (mm)."""
    import dolfinx.mesh as dmesh

    msh = unit_cube(MPI.COMM_SELF, 2)
    prob = HyperelasticProblem(msh, NeoHookean.from_E_nu(1.0, 0.3), disc=Discretisation("p1"))
    for a in range(3):
        prob.fix(_facets(msh, a, 0.0), components=(a,))
    fac = _facets(msh, 0, 1.0)
    mt = dmesh.meshtags(msh, 2, fac, np.full(len(fac), 1, dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=mt)
    t = fem.Constant(msh, 0.0)
    prob.add_residual(t * prob.vu[0] * ds(1))

    def set_load(s):
        t.value = 1.5 * s

    solve(prob, set_load, newton=NewtonOptions(linesearch=line_search, inversion_guard=guard,
                                               max_it=50),
          stepping=LoadStepping(initial=1.0 / steps, min_step=1.0 / steps,
                                max_step=1.0 / steps))
    return float(prob.displacement().x.array.reshape(-1, 3)[:, 0].min())


def test_inversion_guard_turns_an_inverting_full_step_into_a_converging_one():
    """A 1.5 MPa compressive traction on an E = 1 MPa cube in one load step: the first full
    Newton step (the linear response, strain -1.5) inverts every cell, so full steps give a NaN
    residual (SNES -4); with the guard (J kept >= 0.1 x its value per step) the same full-step
    Newton converges to the solution of 40 small steps."""
    with pytest.raises(SolverError, match="NAN"):
        _traction_cube(0.0, "basic", 1)
    ref = _traction_cube(0.0, "bt", 40)
    assert -0.7 < ref < -0.5  # lambda ~ 0.39 at 1.5 MPa nominal stress
    assert _traction_cube(0.1, "basic", 1) == pytest.approx(ref, abs=1e-8)


def test_admissible_step_of_the_inversion_guard():
    from handfe.step_guard import admissible_step

    eye = np.eye(3)[None]
    # det(I - s diag(2, 0, 0)) = 1 - 2 s >= 0.1 for s <= 0.45: the grid point 14/32 below it
    assert admissible_step(eye, np.diag([2.0, 0, 0])[None], 0.1) == pytest.approx(14 / 32)
    assert admissible_step(eye, -np.diag([2.0, 0, 0])[None], 0.1) == 1.0  # stretching
    # a step that inverts at s ~ 1e-6 is cut to the geometric grid below it
    s = admissible_step(eye, np.diag([1e6, 0, 0])[None], 0.1)
    assert 0 < s < 0.9e-6
    # an already inverted cell is ignored, the others still count
    A = np.stack([np.diag([-1.0, 1, 1]), np.eye(3)])
    B = np.stack([np.zeros((3, 3)), np.diag([2.0, 0, 0])])
    assert admissible_step(A, B, 0.1) == pytest.approx(14 / 32)


def test_mumps_lu_ksp_frees_its_factor():
    """Repeated factorisations with mumps_lu_ksp + destroy() do not grow memory. The pattern it
    replaces (a local ``pc = ksp.getPC()`` alive at ``ksp.destroy()``) kept every LU factor
    (+22 MB per solve on a 40,000-dof Laplacian, petsc4py 3.18), and the torque iterations
    of a muscles run, one condensed tangent each, ran 24 GB out (both patterns side by side:
    ``benchmarks/ksp_factor_memory.py``)."""
    from dolfinx import mesh

    from handfe.solver import mumps_lu_ksp, resident_memory_mb

    msh = mesh.create_unit_square(MPI.COMM_SELF, 200, 200)
    V = fem.FunctionSpace(msh, ("CG", 1))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    A = fem_petsc.assemble_matrix(fem.form((ufl.inner(ufl.grad(u), ufl.grad(v)) + u * v)
                                           * ufl.dx))
    A.assemble()
    b = A.createVecRight()
    b.set(1.0)
    x = b.duplicate()
    rss = []
    for _ in range(6):
        ksp = mumps_lu_ksp(MPI.COMM_SELF, A)
        ksp.solve(b, x)
        assert ksp.getConvergedReason() > 0
        ksp.destroy()
        rss.append(resident_memory_mb())
    for o in (A, b, x):
        o.destroy()
    assert rss[-1] - rss[1] < 20.0, f"memory grew {rss[-1] - rss[1]:.0f} MB over 4 solves: {rss}"

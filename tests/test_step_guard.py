"""The inversion guard (:mod:`handfe.step_guard`) on the grasp's Newton solver.

The two-bone Ogden block of the torque-tangent test (p1-p1s, NumPy kernel) is turned by its
two rigid "bones" in one go, without the tissue-motion predictor: Newton's first step is the
linear response to the bone motion, which inverts cells near the bones when the turn is large.
Without the guard, full steps give a NaN residual (SNES -4) and backtracking, which sees only
the residual norm, fails (-6) at the larger turn; with the guard (J kept >= 0.1 x its value per
step) both converge, to the state backtracking reaches where it can. Runs on 1 and 2 ranks."""

import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI
from test_grasp_torque_jacobian import _block, _chain  # pytest puts tests/ on sys.path

from handfe.grasp.fe import TwoFormNewton


def _turn(angles, line_search: str, keep: float, max_it: int = 60):
    comm = MPI.COMM_WORLD
    msh, problem, bc, ds = _block(comm)
    k = fem.Constant(msh, 1e-3)  # MPa/mm: the soft foundation of the torque-tangent test
    problem.add_residual(k * ufl.inner(ufl.split(problem.w)[0], problem.vu) * ds(7))
    solver = TwoFormNewton(problem, max_it=max_it, guard_keep=keep)
    bc.set(_chain(np.asarray(angles))[0])
    ok, its, reason = solver.solve(line_search)
    return ok, reason, solver, problem


@pytest.mark.mpi
def test_guarded_newton_converges_where_full_steps_invert_cells():
    ang = [0.5, -0.8]  # rad
    ok, reason, _, _ = _turn(ang, "basic", 0.0)
    assert not ok and reason == "-4"  # DIVERGED_FNORM_NAN: the full step inverted cells
    ok, reason, solver, problem = _turn(ang, "basic", 0.1)
    assert ok, reason
    assert solver.guard.shortened >= 1 and 0.0 < solver.guard.smallest < 1.0
    assert problem.tissue_volume()["min_cell_J"] > 0.1
    w_guard = problem.w.x.array.copy()
    ok, reason, _, problem = _turn(ang, "bt", 0.0)
    assert ok, reason
    comm = MPI.COMM_WORLD
    scale = comm.allreduce(float(np.abs(problem.w.x.array).max()), op=MPI.MAX)
    diff = comm.allreduce(float(np.abs(problem.w.x.array - w_guard).max()), op=MPI.MAX)
    assert diff <= 1e-6 * scale


@pytest.mark.mpi
def test_guarded_backtracking_converges_where_plain_backtracking_fails():
    ang = [0.8, -1.2]  # rad
    ok, reason, _, _ = _turn(ang, "bt", 0.0)
    assert not ok  # -6: the line search found no decrease along the inverting direction
    ok, reason, solver, problem = _turn(ang, "bt", 0.1)
    assert ok, reason
    assert solver.guard.shortened >= 1
    assert problem.tissue_volume()["min_cell_J"] > 0.1


@pytest.mark.mpi
def test_a_failed_solve_says_when_the_guard_kept_its_steps_short():
    # two iterations are not enough for the larger turn: the reason names the guard's part
    ok, reason, solver, _ = _turn([0.8, -1.2], "basic", 0.1, max_it=2)
    assert not ok
    assert reason.startswith("-5; inversion guard shortened ")  # DIVERGED_MAX_IT
    assert "of 2 steps" in reason and "smallest cell J " in reason
    # ... and where that cell is: its centre, the same on every rank, inside the block
    c = solver.guard.min_J_centre
    assert c is not None and reason.endswith(" at ({:.1f}, {:.1f}, {:.1f}) mm".format(*c))
    assert np.all(c > 0.0) and np.all(c < [10.0, 6.0, 4.0])
    assert all(np.array_equal(c, o) for o in MPI.COMM_WORLD.allgather(c))
    ok, reason, _, _ = _turn([0.8, -1.2], "bt", 0.1)  # converged: the plain reason
    assert ok and "guard" not in reason


@pytest.mark.mpi
def test_the_guard_note_names_the_place_in_the_solver_s_words():
    """``TwoFormNewton.locate`` (the grasp sets it to ``outputs.describe_cell``: "2.7 mm under the
    thumb/proximal skin") replaces the coordinates, and is called on every rank."""
    comm = MPI.COMM_WORLD
    msh, problem, bc, ds = _block(comm)
    k = fem.Constant(msh, 1e-3)
    problem.add_residual(k * ufl.inner(ufl.split(problem.w)[0], problem.vu) * ds(7))
    solver = TwoFormNewton(problem, max_it=2, guard_keep=0.1)
    seen = []
    solver.locate = lambda centre: seen.append(centre) or f"{centre[2]:.1f} mm above the base"
    bc.set(_chain(np.array([0.8, -1.2]))[0])
    ok, _, reason = solver.solve("basic")
    assert not ok and reason.endswith(" mm above the base)") and " at (" not in reason
    assert len(seen) == 1 and np.array_equal(seen[0], solver.guard.min_J_centre)


@pytest.mark.mpi
@pytest.mark.parametrize("angles", [[0.8, -1.2], [0.6, -0.9]])
def test_guard_damping_shifts_the_jacobian_not_the_solution(angles):
    """``TwoFormNewton.damping`` (workflow key ``solver.guard_damping``) adds a Levenberg-
    Marquardt shift to the Jacobian's displacement diagonal once the guard cuts a step below
    0.1 of its length. Full steps with the guard at 0.5 take the block there (the shift
    reaches 0.1) and converge to the undamped state: the residual, so the solution, is the
    same (to 1e-8 relative, measured 3e-13 and 8e-12 on 1 and 2 ranks). On this block the
    damping is not always faster, nor always convergent (docs/grasp.md, thirty-sixth session):
    this test is about what it must not change."""
    comm = MPI.COMM_WORLD
    u = {}
    for damping in (False, True):
        msh, problem, bc, ds = _block(comm)
        k = fem.Constant(msh, 1e-3)
        problem.add_residual(k * ufl.inner(ufl.split(problem.w)[0], problem.vu) * ds(7))
        solver = TwoFormNewton(problem, max_it=60, guard_keep=0.5)
        solver.damping = damping
        bc.set(_chain(np.asarray(angles))[0])
        ok, _, reason = solver.solve("basic")
        assert ok, reason
        assert (solver.damping_max >= 0.1) == damping
        u[damping] = problem.w.sub(0).collapse().x.array
    diff = comm.allreduce(float(np.sum((u[True] - u[False]) ** 2)), op=MPI.SUM)
    norm = comm.allreduce(float(np.sum(u[False] ** 2)), op=MPI.SUM)
    assert np.sqrt(diff / norm) < 1e-8


@pytest.mark.mpi
def test_guard_damping_shifts_only_free_displacement_rows():
    """The shift acts on the owned displacement rows off the Dirichlet (bone) dofs: there the
    diagonal becomes K_ii + shift |K_ii|; pressure and Dirichlet rows keep theirs. Only in the
    Jacobians of Newton's solves: the torque Newton's condensed tangent stays the true one."""
    comm = MPI.COMM_WORLD
    msh, problem, bc, ds = _block(comm)
    k = fem.Constant(msh, 1e-3)
    problem.add_residual(k * ufl.inner(ufl.split(problem.w)[0], problem.vu) * ds(7))
    solver = TwoFormNewton(problem, max_it=5, guard_keep=0.5)
    x = problem.w.vector
    diag = {}
    for shift in (0.0, 0.5):
        solver.damping_shift = shift
        solver._jacobian(solver.snes, x, solver.A, solver.A)  # as the SNES asks for it
        diag[shift] = solver.A.getDiagonal().array.copy()
    # ... and the condensed tangent's call (no SNES) gets the true Jacobian
    solver._jacobian(None, x, solver.A, solver.A)
    np.testing.assert_array_equal(solver.A.getDiagonal().array, diag[0.0])
    W = problem.W
    n = W.dofmap.index_map.size_local
    is_u = np.zeros(n, dtype=bool)
    umap = np.asarray(W.sub(0).collapse()[1])
    is_u[umap[umap < n]] = True
    fixed = np.zeros(n, dtype=bool)
    for b in problem.bcs:
        i = b.dof_indices()[0]
        fixed[i[i < n]] = True
    free = is_u & ~fixed
    assert comm.allreduce(int(free.sum()), op=MPI.SUM) > 0
    assert comm.allreduce(int((is_u & fixed).sum()), op=MPI.SUM) > 0
    np.testing.assert_allclose(diag[0.5][free], diag[0.0][free] + 0.5 * np.abs(diag[0.0][free]),
                               rtol=1e-12)
    np.testing.assert_array_equal(diag[0.5][~free], diag[0.0][~free])

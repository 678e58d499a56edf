"""Loose intermediate solves, tight reported state (``solver.closing_atol_N``, issue 6).

The closing steps of a grasp stop Newton at ``closing_atol_N`` (Newton on the contact kinks
stalls at 1e-4..1e-2 N, docs/grasp.md); ``GraspFE._tighten`` then solves the last state to the
tight tolerance with the same data. Checked on the two-bone Ogden block of the torque-tangent
test: the loose solve stops early within its tolerance, the tightened state is the tight
solve's, and the tolerance is restored after the loose block even when it raises.
"""

import contextlib
from types import SimpleNamespace

import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI
from test_grasp_torque_jacobian import _block, _chain  # pytest puts tests/ on sys.path

from handfe.grasp.config import SolverSpec
from handfe.grasp.fe import TwoFormNewton
from handfe.grasp.scene import GraspFE


class _Scene:
    """The pieces of GraspFE that _loose/_tighten use."""

    def __init__(self, problem, solver, closing_atol_N):
        self.problem, self.solver = problem, solver
        # "initial": no lagged modulus; these tests are about the loose and tight solves
        self.wf = SimpleNamespace(solver=SolverSpec(closing_atol_N=closing_atol_N,
                                                    stabilisation_modulus="initial"),
                                  element="p1-p1s")
        self.steps, self.log = [], []

    def say(self, msg):
        self.log.append(msg)

    _loose = GraspFE._loose
    _tighten = GraspFE._tighten
    _residual_norm = GraspFE._residual_norm
    _set_state = GraspFE._set_state
    _lag_stabilisation = GraspFE._lag_stabilisation


@pytest.mark.mpi
def test_loose_closing_solves_then_one_tight_solve():
    comm = MPI.COMM_WORLD
    msh, problem, bc, ds = _block(comm)
    k = fem.Constant(msh, 1e-3)  # MPa/mm: the soft foundation of the torque-tangent test
    problem.add_residual(k * ufl.inner(ufl.split(problem.w)[0], problem.vu) * ds(7))
    solver = TwoFormNewton(problem, max_it=40)
    scene = _Scene(problem, solver, closing_atol_N=1e-2)
    old = bc.ubc.x.array.copy()
    bc.set(_chain(np.radians([3.0, -2.0]))[0])
    bc.predict(old)
    w_start = problem.w.x.array.copy()

    ok, its_tight, reason = solver.solve()
    assert ok, reason
    w_tight = problem.w.x.array.copy()
    assert scene._residual_norm() <= 1e-9

    scene._set_state(w_start)
    with scene._loose():
        assert solver.atol == 1e-2 and solver.stall_atol >= 1e-2
        ok, its_loose, reason = solver.solve()
        assert ok, reason
    assert solver.atol == 1e-9  # restored
    r_loose = scene._residual_norm()
    assert r_loose <= 1e-2
    assert its_loose < its_tight  # the quadratic tail is not paid for an intermediate state

    scene._tighten()
    assert scene.steps[-1]["step"] == "tight solve" and scene.steps[-1]["converged"]
    assert scene._residual_norm() <= 1e-9
    scale = float(np.abs(w_tight).max())
    diff = comm.allreduce(float(np.abs(problem.w.x.array - w_tight).max()), op=MPI.MAX)
    assert diff <= 1e-6 * scale


def test_loose_block_restores_the_tolerance_on_error():
    solver = SimpleNamespace(atol=1e-9, stall_atol=1e-4)
    solver.set_atol = lambda a: setattr(solver, "atol", a)
    scene = _Scene(None, solver, closing_atol_N=1e-2)
    with pytest.raises(RuntimeError), scene._loose():
        assert solver.atol == 1e-2
        raise RuntimeError("a closing step failed")
    assert (solver.atol, solver.stall_atol) == (1e-9, 1e-4)
    # 0 = every solve tight: nothing changes, and there is nothing to tighten
    off = _Scene(None, solver, closing_atol_N=0.0)
    with off._loose():
        assert solver.atol == 1e-9
    off._tighten()
    assert off.steps == []


class _FinalPhase:
    """Stand-in for GraspFE._final_phase: the state is [penetration mm]; the tight Uzawa phase
    stops at 0.058 mm (a failed re-solve), the loose one reaches 0.005 mm, and the tight solve
    after it converges or not (``tight_ok``)."""

    def __init__(self, tight_ok: bool, closing_atol_N: float = 1e-2):
        self.tight_ok = tight_ok
        self.wf = SimpleNamespace(solver=SolverSpec(closing_atol_N=closing_atol_N))
        self.solver = SimpleNamespace(atol=1e-9)
        self.problem = SimpleNamespace(w=SimpleNamespace(x=SimpleNamespace(
            array=np.array([0.2]))))
        self.contact = SimpleNamespace(penetration_tol_mm=0.01, uzawa=SimpleNamespace(
            penetration=lambda: float(self.problem.w.x.array[0])))
        self.data = {"lambda_n": "tight"}
        self.loose = False
        self.steps, self.log, self.creep = [], [], []

    def say(self, msg):
        self.log.append(msg)

    def augment(self, creep=True):
        self.problem.w.x.array[:] = 0.005 if self.loose else 0.058
        self.data = {"lambda_n": "loose" if self.loose else "tight"}
        self.creep.append(creep)

    @contextlib.contextmanager
    def _loose(self):
        self.loose = True
        try:
            yield
        finally:
            self.loose = False

    def _scale_loose(self, forces):
        assert self.loose

    def digit_forces(self):
        return {}

    def _tighten(self):
        return self.tight_ok

    def _contact_data(self):
        return dict(self.data)

    def _set_contact_data(self, data):
        self.data = dict(data)

    def _set_state(self, w):
        self.problem.w.x.array[:] = w

    def _residual_norm(self):
        return 0.0

    _final_phase = GraspFE._final_phase


@pytest.mark.parametrize("tight_ok", [True, False])
def test_final_phase_goes_on_loosely_and_keeps_only_a_tight_better_state(tight_ok):
    scene = _FinalPhase(tight_ok)
    scene._final_phase()
    pen = scene.contact.uzawa.penetration()
    # the tight phase also removes the stick creep; the loose continuation only aims at the
    # penetration target (a creep flat at 0.02 mm kept the reduced cylinder's going for 12
    # updates of ~100 s)
    assert scene.creep == [True, False]
    if tight_ok:  # loose updates from 0.058 mm, then a converged tight solve: kept
        assert pen == 0.005 and scene.data == {"lambda_n": "loose"}
    else:  # the tight solve failed: the tight state and the data it was solved with come back
        assert pen == 0.058 and scene.data == {"lambda_n": "tight"}
        assert scene.steps[-1]["step"] == "restored tight state"
    # without loose solves (closing_atol_N = 0) the tight phase's result is final
    off = _FinalPhase(tight_ok, closing_atol_N=0.0)
    off._final_phase()
    assert off.contact.uzawa.penetration() == 0.058 and off.log == []


def test_tight_final_solve_keeps_the_data_of_the_stalled_state():
    # the muscles mode's final state (stopped at a grip-scaled stall) is solved tight with the
    # data it was solved with: the p1-p1s stabilisation is not lagged first (a new modulus is
    # new data: the coarse cylinder went from ~1e-2 to 0.41 N and the solve failed), and a
    # state already within the stall tolerance is left alone
    norms = [5e-3, 1e-10]  # before and after the solve
    events = []
    scene = SimpleNamespace(
        wf=SimpleNamespace(solver=SolverSpec()), steps=[],
        solver=SimpleNamespace(atol=1e-9, stall_atol=1e-4,
                               solve=lambda: (events.append("solve"), (True, 3, "2"))[1]),
        problem=SimpleNamespace(w=SimpleNamespace(x=SimpleNamespace(array=np.zeros(2)))),
        _residual_norm=lambda: norms.pop(0),
        _lag_stabilisation=lambda: events.append("lag"), say=lambda m: None)
    assert GraspFE._tighten(scene, stalled=True)
    assert events == ["solve"] and scene.steps[-1]["converged"]
    events.clear()
    norms[:] = [5e-5]
    assert GraspFE._tighten(scene, stalled=True) and events == []

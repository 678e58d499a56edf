"""Step cutting of one bone step (``GraspFE._go_to``) with a stand-in FE solver (no FE): what a
cut retries, and what a failed solve does with a friction return mapping it applied."""

from types import SimpleNamespace

import numpy as np
import pytest

from handfe.errors import SolverError
from handfe.grasp.scene import GraspFE


class _Solver:
    """Stand-in FE Newton: converges when ``ok(fraction, mapped)`` says so; ``fraction`` is the
    end of the attempted sub-step, ``mapped`` whether the return mapping was applied."""

    line_search = "bt"
    guard_note = ""

    def __init__(self, scene, ok):
        self.scene, self.ok = scene, ok
        self.history = [1.0]
        self.tries: list[tuple[float, float, bool]] = []  # (start, end, mapped)

    def solve(self, line_search=None):
        sc = self.scene
        start, end = sc._start, sc.bc.frac
        mapped = bool(sc.contact.lambda_t.x.array[0] != 0.0)
        self.tries.append((start, end, mapped))
        good = self.ok(start, end, mapped)
        if good:
            sc.problem.w.x.array[:] = end
        return good, 5, "" if good else "-5"  # <= 8: the next sub-step doubles

    def continue_after_stall(self):
        return (False, 0, "-5")


def _scene(ok) -> GraspFE:
    """A GraspFE without FE: the state is one number, the fraction of the bone step reached."""
    sc = object.__new__(GraspFE)
    sc._start = 0.0
    arr = SimpleNamespace(array=np.zeros(1), scatter_forward=lambda: None)
    sc.problem = SimpleNamespace(w=SimpleNamespace(x=arr))
    sc.kin = SimpleNamespace(clamp=lambda th: th, skeleton=lambda th: None,
                             motions=lambda skel: "target")
    sc.theta, sc.motions, sc._substep = np.zeros(1), "start", 1.0
    bc = SimpleNamespace(frac=0.0, ubc=SimpleNamespace(x=SimpleNamespace(array=np.zeros(1))))

    def bc_set(target, frac, prev):
        bc.frac = frac if target == "target" else 0.0
        bc.ubc.x.array[:] = bc.frac

    bc.set, bc.predict = bc_set, lambda old: None
    sc.bc = bc
    c = SimpleNamespace(translation=SimpleNamespace(value=np.zeros(3)), history_due=False,
                        lambda_t=SimpleNamespace(x=SimpleNamespace(array=np.zeros(1))))

    def apply_history():
        if c.history_due:
            c.lambda_t.x.array[:] = 1.0
            c.history_due = False

    c.apply_history = apply_history
    c.on_step = lambda t, r, defer=False: None
    sc.contact = c
    sc._dw, sc._dbc, sc._t_response, sc._theta_response = None, 0.0, [], None
    sc._hold_history, sc._fallback_ls = True, "basic"
    sc.steps, sc.cuts, sc.dropped_mappings = [], 0, 0
    sc.predictor_wins = {"extension": 0, "secant": 0, "tangent": 0}
    sc.messages = []
    sc.say = sc.messages.append
    sc._lag_stabilisation = lambda: None

    def set_state(a):
        sc.problem.w.x.array[:] = a
        sc._start = float(a[0])

    sc._set_state = set_state
    sc._contact_data = lambda: {"lambda_t": c.lambda_t.x.array.copy(), "due": c.history_due}

    def set_data(d):
        c.lambda_t.x.array[:] = d["lambda_t"]
        c.history_due = d["due"]

    sc._set_contact_data = set_data
    sc._norm = lambda a: float(np.linalg.norm(a))

    def snapshot():
        return {"w": arr.array.copy(), "theta": sc.theta.copy(), "motions": sc.motions,
                "data": sc._contact_data()}

    def restore(snap):
        set_state(snap["w"])
        sc.theta, sc.motions = snap["theta"].copy(), snap["motions"]
        set_data(snap["data"])

    sc._snapshot, sc._restore = snapshot, restore
    sc._residual_norm = lambda: 1.0  # the predictors tie: the first (extension) wins
    return sc


def _run(sc, ok, max_cuts=6):
    sc.solver = _Solver(sc, ok)
    orig = sc.solver.solve

    def solve(line_search=None):
        res = orig(line_search)
        if res[0]:
            sc._start = sc.bc.frac
        return res

    sc.solver.solve = solve
    GraspFE._go_to(sc, np.ones(1), label="step", max_cuts=max_cuts)
    return sc.solver.tries


def test_a_cut_after_a_doubled_sub_step_halves_what_was_tried():
    # coarse spherical run SQ: sub-step 0.5 converged in <= 8 iterations (the size doubles to
    # 1), the rest failed, and the "cut" retried the same remainder 0.5 -> 1 (100 s, the same
    # residuals). Now the retry is 0.5 -> 0.75
    sc = _scene(None)
    sc._substep = 0.5
    tries = _run(sc, lambda a, b, m: b - a <= 0.25 + 1e-12 or b <= 0.5)
    ends = [(a, b) for a, b, _ in tries]
    assert ends[:3] == [(0.0, 0.5), (0.5, 1.0), (0.5, 0.75)]
    assert len(set(ends)) == len(ends)  # never the same sub-step twice
    assert sc.problem.w.x.array[0] == 1.0 and sc.cuts == 1


def test_a_failed_solve_drops_the_friction_return_mapping_it_applied():
    # runs K and SQ: after a failed round of the final Uzawa phase, the next torque step's
    # solve applied the due return mapping and failed at every cut. The failed solve now puts
    # back the stick data the converged state balances, and the retry goes without it
    sc = _scene(None)
    sc.contact.history_due = True
    tries = _run(sc, lambda a, b, m: not m)
    assert tries == [(0.0, 1.0, True), (0.0, 0.5, False), (0.5, 1.0, False)]
    assert sc.dropped_mappings == 1 and not sc.contact.history_due
    assert sc.contact.lambda_t.x.array[0] == 0.0
    assert any("return mapping" in m and "dropped" in m for m in sc.messages)


def test_a_mapping_that_converges_is_kept():
    sc = _scene(None)
    sc.contact.history_due = True
    tries = _run(sc, lambda a, b, m: True)
    assert tries == [(0.0, 1.0, True)]
    assert sc.dropped_mappings == 0 and sc.contact.lambda_t.x.array[0] == 1.0


def test_failing_step_raises_after_max_cuts_back_at_its_start():
    # sub-step 0 -> 0.25 converged, 0.25 -> 0.5 and -> 0.375 failed: the state goes back to the
    # step's start, where the joint angles and the bones' motions still are (kept at 0.25,
    # the next step would have started by moving the bones back by a quarter step)
    sc = _scene(None)
    sc.contact.history_due = True  # applied by the converged sub-step, due again at the start
    with pytest.raises(SolverError, match="after 4 cuts.*back to its start"):
        _run(sc, lambda a, b, m: b <= 0.25, max_cuts=3)
    assert sc.problem.w.x.array[0] == 0.0 and sc.bc.frac == 0.0
    assert sc.theta[0] == 0.0 and sc.motions == "start"
    assert sc.contact.history_due and sc.contact.lambda_t.x.array[0] == 0.0


class _StallSolver:
    """Stand-in for a re-solve: every solve fails after ``its`` iterations; records the line
    searches tried and the full-step continuations asked for (which adopt their last iterate,
    here the state 7)."""

    max_it = 40

    def __init__(self, its, state):
        self.its, self.state, self.continued, self.tried = its, state, 0, []

    def solve(self, line_search=None):
        self.tried.append(line_search)
        return False, self.its, "-5"

    def continue_after_stall(self):
        self.continued += 1
        self.state[:] = 7.0
        return False, 3, "-4"


@pytest.mark.parametrize("its, continued", [(40, 0), (12, 1)])
def test_a_resolve_goes_on_with_full_steps_only_if_backtracking_stopped_early(its, continued):
    """After backtracking crawled through its whole budget, full steps from its last iterate
    failed in every logged re-solve: the re-solve then fails at once; a stall before the
    budget still gets the continuation. Either way the state and data come back."""
    sc = _resolve_scene("bt", its)
    undone = []
    assert not sc._resolve("Uzawa update 1", lambda: undone.append(True))
    assert sc.solver.continued == continued and sc.solver.tried == ["bt"]
    assert undone == [True] and sc.problem.w.x.array[0] == 1.0
    assert sc.messages[-1].endswith(f"({its + 3 * continued} iterations)")


def test_a_full_step_resolve_that_fails_falls_back_to_backtracking_from_its_start():
    """``resolve_linesearch = "basic"``: full steps that ran out of iterations are followed by
    backtracking from the state before the re-solve, iterations summed."""
    sc = _resolve_scene("basic", 40)
    assert not sc._resolve("Uzawa update 1", lambda: None)
    assert sc.solver.tried == ["basic", "bt"] and sc.solver.continued == 0
    assert "(full steps failed, bt)" in sc.messages[-1]
    assert sc.messages[-1].endswith("(80 iterations)")


def _resolve_scene(line_search: str, its: int) -> GraspFE:
    """A GraspFE for ``_resolve`` only: the state is one number (1 before the re-solve)."""
    sc = object.__new__(GraspFE)
    arr = SimpleNamespace(array=np.array([1.0]), scatter_forward=lambda: None)
    sc.problem = SimpleNamespace(w=SimpleNamespace(x=arr))
    sc.wf = SimpleNamespace(solver=SimpleNamespace(resolve_linesearch=line_search))
    sc._lag_stabilisation = lambda: None
    sc.messages = []
    sc.say = sc.messages.append
    sc.solver = _StallSolver(its, arr.array)

    def set_state(a):
        arr.array[:] = a

    sc._set_state = set_state
    return sc

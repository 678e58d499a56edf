"""Dump the muscles mode's final state, and replay the final solve from the dump.

A muscles run of the coarse cylinder takes ~30 min to reach its final tight solve; experiments
on that solve (docs/grasp.md, twentieth session) need its state, not the run. ``dump`` runs a
workflow and, when the final tight solve starts (``--at full-load``: when the final Uzawa
phase starts), writes ``DIR/dump<rank>.pkl`` (the scene's
snapshot: state, bone motions, contact multipliers, stick anchors, penalty, stabilisation
modulus, joint angles and torque data), every nodal/cell array keyed by its dof coordinates,
because the mesh partition differs between runs. ``replay`` builds the same scene (mesh,
forms: ~20 s), restores the dump on any partition, runs one of the modes below and writes
the outputs to ``DIR/replay-MODE[-smoothingDELTA]`` or ``--out`` (``summary.json`` status,
equilibrium, torque residuals; ``--friction-smoothing DELTA`` rounds the Coulomb cone first;
``--mesh LEVEL`` overrides the workflow's mesh level and ``--set KEY=VALUE`` any key (as
``handfe run --set``), in both actions alike; the dump keeps
``solver.guard_damping``'s shift, which carries across solves):

- ``tighten``: the run's final tight solve (``GraspFE._tighten(stalled=True)``);
- ``final-phase`` (from a dump ``--at full-load``): the final Uzawa phase and tight solve
  (``GraspFE._final_muscle_phase``), e.g. with other ``[solver]`` keys in the workflow;
- ``derivatives``: the Newton direction d at the state, the residual norm along -d, and
  forward / backward finite differences of the tissue and contact forms along d against the
  assembled tangent (a kink of the law shows as forward != backward), and where d is large;
- ``cone``: the skin area whose contact quadrature points sit within a tolerance of the
  normal-contact switch (lambda_n - k_n g = 0) or of the Coulomb cone (|trial| = mu p);
- ``linesearch``: the tight solve with PETSc's l2, cp and nleqerr line searches;
- ``cells``: the tissue's volume change, the smallest cells' pressure against their bulk
  modulus (the law's J for it), and the ten smallest-J tissue cells (where, how deep);
- ``balance``: the tight solve, then torque Newton iterations with tight FE solves (no
  grip-scaled stall tolerance), then the tight solve again.

    mpirun -n 2 .venv/bin/python scripts/final_state.py dump workflows/cylindrical_muscles.toml D
    mpirun -n 2 .venv/bin/python scripts/final_state.py replay workflows/cylindrical_muscles.toml \
        D --mode derivatives
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

from handfe.grasp import scene as S
from handfe.solver import mumps_lu_ksp

#: the scene attributes the torques and the torque Newton need besides the snapshot
EXTRA = ("tau_muscle", "muscle_load", "force_target", "coupled", "at_limit", "closing_mu")
#: snapshot arrays (the contact ones live under snapshot["contact"])
STATE = ("w", "ubc", "mu0")
CONTACT = ("lambda_n", "lambda_t", "u_ref")


def dof_keys(V) -> np.ndarray:
    """(x, y, z, sub-space, component) of every local entry of a function space's arrays
    (ghosts included), rounded: the same entry has the same key on any partition."""
    mixed = V.ufl_element().family() == "Mixed"
    im = V.dofmap.index_map
    keys = np.full(((im.size_local + im.num_ghosts) * V.dofmap.index_map_bs, 5), np.nan)
    parts = [V.sub(i).collapse() for i in range(V.num_sub_spaces)] if mixed else [(V, None)]
    for i, (Vi, m) in enumerate(parts):
        x = Vi.tabulate_dof_coordinates()
        bs = Vi.dofmap.index_map_bs
        k = np.zeros((x.shape[0] * bs, 5))
        for c in range(bs):
            k[c::bs, :3], k[c::bs, 4] = x, c
        k[:, 3] = i
        if m is None:
            keys = k
        else:
            keys[np.asarray(m)] = k
    return np.round(keys, 6)


def _spaces(scene) -> dict:
    c = scene.contact
    out = {"w": scene.problem.W, "ubc": scene.bc.ubc.function_space,
           "mu0": scene.problem.mu0.function_space}
    out.update({n: getattr(c, n).function_space for n in CONTACT if getattr(c, n) is not None})
    return out


def _write_dump(scene, folder: Path, what: str) -> None:
    data = {"snap": scene._snapshot(),
            "extra": {k: getattr(scene, k, None) for k in EXTRA},
            # solver.guard_damping's Levenberg-Marquardt shift, which carries across solves
            "damping_shift": scene.solver.damping_shift,
            "keys": {k: dof_keys(V) for k, V in _spaces(scene).items()}}
    (folder / f"dump{MPI.COMM_WORLD.rank}.pkl").write_bytes(pickle.dumps(data))
    scene.say(f"{what} dumped to {folder}")


def dump(workflow: str | S.Workflow, folder: Path, at: str = "final",
         mesh: str | None = None) -> None:
    """Run ``workflow``, dumping the state where the final tight solve starts (``at`` =
    "final") or where the final Uzawa phase starts, the full EMG load balanced ("full-load")."""
    folder.mkdir(parents=True, exist_ok=True)
    if at == "final":
        tighten = S.GraspFE._tighten

        def patched(self, *, stalled: bool = False) -> bool:
            if stalled and not getattr(self, "_dumped", False):
                self._dumped = True
                _write_dump(self, folder, "final state")
            return tighten(self, stalled=stalled)

        S.GraspFE._tighten = patched
    else:
        phase = S.GraspFE._final_muscle_phase

        def patched_phase(self) -> None:
            _write_dump(self, folder, "state at full load (before the final Uzawa phase)")
            phase(self)

        S.GraspFE._final_muscle_phase = patched_phase
    S.run_workflow(workflow, mesh=mesh, out_dir=folder / "run")


def restore(scene, folder: Path) -> None:
    """Set ``scene`` to the dumped state (any partition)."""
    dumps = [pickle.loads(f.read_bytes()) for f in sorted(folder.glob("dump*.pkl"))]
    if not dumps:
        raise SystemExit(f"no dump*.pkl in {folder}: run `dump` first")
    snap = dict(dumps[0]["snap"])
    snap["contact"] = dict(snap["contact"])
    from scipy.spatial import cKDTree

    # (sub-space, component) far apart, so only the same entry's coordinates can match
    sep = np.array([1.0, 1.0, 1.0, 1e4, 1e4])
    for name, V in _spaces(scene).items():
        keys = np.concatenate([d["keys"][name] for d in dumps])
        arr = np.concatenate([d["snap"][name] if name in STATE else d["snap"]["contact"][name]
                              for d in dumps])
        # nearest, not exact, keys (a rounded coordinate near a rounding boundary may flip);
        # another mesh (HXT meshes differ run to run) is named instead of a KeyError
        dist, idx = cKDTree(keys * sep).query(dof_keys(V) * sep)
        if dist.max(initial=0.0) > 1e-4:
            raise SystemExit(f"{name}: the dump's mesh is not this mesh (a dof {dist.max():.2g} "
                             "mm from any dumped one)")
        (snap if name in STATE else snap["contact"])[name] = arr[idx]
    snap["dw"], snap["dbc"] = None, None  # the secant predictor's data (partition-bound)
    scene._restore(snap)
    for k, v in dumps[0]["extra"].items():
        setattr(scene, k, v)
    scene.solver.damping_shift = dumps[0].get("damping_shift", 0.0)


def derivatives(scene) -> None:
    from dolfinx.fem import petsc as fem_petsc
    from petsc4py import PETSc

    sol, prob, say = scene.solver, scene.problem, scene.say
    x = prob.w.vector.copy()
    b = x.duplicate()
    sol._residual(None, x, b)
    sol._jacobian(None, x, sol.A, sol.A)
    ksp = mumps_lu_ksp(prob.comm, sol.A)
    d = x.duplicate()
    ksp.solve(b, d)
    ksp.destroy()
    say(f"|R| {b.norm():.3e} N, Newton direction |d| {d.norm():.3e}, max "
        f"{d.norm(PETSc.NormType.INFINITY):.3e}")
    for t in (1.0, 0.5, 0.1, 1e-2, 1e-3):
        y = x.copy()
        y.axpy(-t, d)
        r = x.duplicate()
        sol._residual(None, y, r)
        say(f"  |R(w - {t:g} d)| / ((1 - {t:g}) |R|) = {r.norm() / ((1 - t) * b.norm()):.4g}"
            if t < 1 else f"  |R(w - d)| = {r.norm():.3e} N")

    def vec(i: int, y):
        y.copy(prob.w.vector)
        prob.w.x.scatter_forward()
        prob.update(tangent=False)
        v = fem_petsc.assemble_vector(sol.L[i])
        v.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return v

    for i, name in enumerate(("tissue", "contact")):
        x.copy(prob.w.vector)
        prob.w.x.scatter_forward()
        prob.update()
        A = fem_petsc.assemble_matrix(sol.a[i])
        A.assemble()
        Ad = x.duplicate()
        A.mult(d, Ad)
        for eps in (1e-4, 1e-6):
            yp, ym = x.copy(), x.copy()
            yp.axpy(eps, d)
            ym.axpy(-eps, d)
            v0, vp, vm = vec(i, x), vec(i, yp), vec(i, ym)
            fwd, bwd = (vp - v0) * (1.0 / eps), (v0 - vm) * (1.0 / eps)
            say(f"  {name} form, eps {eps:g}: |A d| {Ad.norm():.3e}, |forward - A d| "
                f"{(fwd - Ad).norm():.3e}, |backward - A d| {(bwd - Ad).norm():.3e}")
    x.copy(prob.w.vector)
    prob.w.x.scatter_forward()
    n = d.getLocalSize()
    for i, name in enumerate(("displacement", "pressure")):
        Vi, m = prob.W.sub(i).collapse()
        m = np.asarray(m)
        m = m[m < n]
        v = d.getArray()[m]
        bs = Vi.dofmap.index_map_bs
        at = Vi.tabulate_dof_coordinates()[int(np.abs(v).argmax()) // bs] if len(v) else None
        big = int(np.count_nonzero(np.abs(v) > 0.1 * np.abs(v).max(initial=0.0)))
        print(f"rank {prob.comm.rank}: d {name} max {np.abs(v).max(initial=0.0):.3e} at {at}, "
              f"{big} entries above 10 % of it", flush=True)


def cone(scene) -> None:
    import ufl
    from dolfinx import fem

    c = scene.contact
    T = c.terms
    arg = c.lambda_n - c.k_n * T.gap
    trial = T.trial_traction
    off = abs(ufl.sqrt(ufl.max_value(ufl.dot(trial, trial), 1e-24)) - c._mu_c * T.pressure)
    ds = ufl.Measure("ds", domain=scene.problem.mesh, subdomain_data=scene.skin_tags,
                     metadata=scene.problem.ds_metadata)(1)

    def area(expr) -> float:
        return scene.problem.comm.allreduce(fem.assemble_scalar(fem.form(expr * ds)),
                                            op=MPI.SUM)

    for tol in (1e-14, 1e-12, 1e-10, 1e-8):
        a = area(ufl.conditional(ufl.le(abs(arg), tol), 1.0, 0.0))
        b = area(ufl.conditional(ufl.And(ufl.le(off, tol), ufl.gt(T.pressure, 0.0)), 1.0, 0.0))
        scene.say(f"  tol {tol:g} MPa: area at the contact switch {a:.3e} mm2, on the Coulomb "
                  f"cone {b:.3e} mm2 (skin {area(1.0):.0f} mm2)")


def cells(scene) -> None:
    """The tissue's volume change (``GraspProblem.tissue_volume``) and the ten smallest-J
    cells (:func:`handfe.grasp.outputs.smallest_tissue_cells`: J, the region of the nearest
    outer skin facet and its distance, mm, reference configuration, and the signed distance
    of the deformed centre to the object, mm)."""
    from handfe.grasp.outputs import smallest_tissue_cells

    prob = scene.problem
    scene.say("tissue volume: " + ", ".join(f"{k} {v:.4g}"
                                             for k, v in prob.tissue_volume().items()))
    # is a small J the law's answer to the pressure (J = 1 + p / kappa) or the element's
    # volume trading? the cell mean pressure p against the cell's bulk modulus kappa
    tissue, J = prob.tissue_cell_J()
    pdof = prob.W.sub(1).dofmap.list.array.reshape(-1, 4)
    p = prob.w.x.array[pdof[tissue]].mean(axis=1)
    kdof = prob.inv_kappa.function_space.dofmap.list.array
    pk = p * prob.inv_kappa.x.array[kdof[tissue]]
    J, p, pk = (np.concatenate(prob.comm.allgather(a)) for a in (J, p, pk))
    low = np.argsort(J, kind="stable")[:15]
    scene.say(f"cells at J < 0.2: {np.count_nonzero(J < 0.2)}, at J < 0.1: "
              f"{np.count_nonzero(J < 0.1)}; the 15 smallest (J {J[low].min():.3g}-"
              f"{J[low].max():.3g}) carry p {1e3 * p[low].min():.0f} to {1e3 * p[low].max():.0f}"
              f" kPa, p / kappa {pk[low].min():.3f} to {pk[low].max():.3f} (the law's J = 1 + "
              f"p / kappa: {1 + pk[low].min():.2f}-{1 + pk[low].max():.2f}); the most "
              f"compressed cell: p / kappa {pk.min():.3f} at J {J[np.argmin(pk)]:.3g}")
    for c in smallest_tissue_cells(prob, scene.model, scene.obstacle,
                                   scene.contact.translation.value, k=10):
        scene.say(f"cell J {c['J']:.3g} at {c['centre_mm']} ({c['nearest_skin']} skin "
                  f"{c['skin_distance_mm']:.2f} mm away; signed distance to the object "
                  f"{c['object_distance_mm']:.2f} mm)")


def linesearch(scene) -> None:
    snap, sol = scene._snapshot(), scene.solver
    for ls in ("l2", "cp", "nleqerr"):
        scene._restore(snap)
        sol._snes[ls] = sol._make_snes(ls, 1e-8, 1e-9, 40)
        ok, its, reason = sol.solve(ls)
        scene.say(f"  line search {ls}: converged {ok}, {its} iterations ({reason}); residuals "
                  + " ".join(f"{h:.1e}" for h in sol.history))
    scene._restore(snap)


def balance(scene) -> None:
    scene._tighten(stalled=True)
    scene.say(f"after the tight solve: largest relative torque residual "
              f"{scene.max_torque_residual():.2e}")
    scene._stall_base = scene.solver.stall_atol
    scene._scale_stall_to_grip = lambda: None  # FE solves to the tight stall tolerance
    with scene._friction_history_per_load():
        ok, why = scene._balance(scene.wf.solver.torque_rtol, label="final, tight FE solves")
    scene.say(f"torque balance with tight FE solves: {ok} ({why})")
    scene._tighten(stalled=True)


def replay(workflow: str | S.Workflow, folder: Path, mode: str, smoothing: float | None = None,
           out: Path | None = None, mesh: str | None = None) -> None:
    def solve_muscles(self) -> None:
        restore(self, folder)
        t0 = time.perf_counter()
        self.say(f"restored the dump: residual {self._residual_norm():.3e} N")
        if smoothing is not None:
            self.contact.friction_smoothing.value = smoothing
            self.say(f"Coulomb cone rounded over +-{smoothing:g} mu p: residual "
                     f"{self._residual_norm():.3e} N")
        {"tighten": lambda s: s._tighten(stalled=True),
         "final-phase": lambda s: s._final_muscle_phase(), "derivatives": derivatives,
         "cone": cone, "linesearch": linesearch, "balance": balance, "cells": cells}[mode](self)
        self.say(f"{mode}: {time.perf_counter() - t0:.1f} s, residual "
                 f"{self._residual_norm():.3e} N")
        self.digit_force_N = self.digit_forces()
        self.torque = self.torques()

    S.GraspFE.solve_muscles = solve_muscles
    tail = "" if smoothing is None else f"-smoothing{smoothing:g}"
    r = S.run_workflow(workflow, mesh=mesh, out_dir=out or folder / f"replay-{mode}{tail}")
    if MPI.COMM_WORLD.rank == 0:
        s = r.summary
        print(f"status {s.get('status')}, equilibrium {s.get('equilibrium_relative_error')}, "
              f"torque residual {s.get('max_relative_torque_residual')}, grip "
              f"{s.get('grip_force_N')} N")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("action", choices=("dump", "replay"))
    ap.add_argument("workflow", help="a muscles-mode workflow TOML")
    ap.add_argument("folder", type=Path, help="where the dump is (written by dump)")
    ap.add_argument("--mode", default="tighten",
                    choices=("tighten", "final-phase", "derivatives", "cone", "linesearch",
                             "balance", "cells"),
                    help="replay: what to run from the dumped state (default tighten)")
    ap.add_argument("--friction-smoothing", type=float, default=None, metavar="DELTA",
                    help="replay: round the Coulomb cone over (1 +- DELTA) mu p before the "
                         "mode runs (handfe.contact.smoothed_cone; default: the run's value)")
    ap.add_argument("--at", default="final", choices=("final", "full-load"),
                    help="dump: where the run's state is dumped - where the final tight solve "
                         "starts (default), or where the final Uzawa phase starts, the full "
                         "EMG load balanced (for replay --mode final-phase)")
    ap.add_argument("--mesh", default=None, metavar="LEVEL",
                    help="mesh level instead of the workflow's (dump and replay alike)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change a workflow key, as handfe run --set (e.g. a [solver] key of "
                         "the final phase to replay: --set solver.muscle_stall_rtol=3e-4)")
    ap.add_argument("--out", type=Path, default=None,
                    help="replay: the output folder (default DIR/replay-MODE[-smoothingDELTA])")
    a = ap.parse_args()
    workflow = a.workflow
    if a.set:
        from handfe.grasp.config import load_workflow, parse_overrides

        workflow = load_workflow(a.workflow, parse_overrides(a.set))
    if a.action == "dump":
        dump(workflow, a.folder, a.at, a.mesh)
    else:
        replay(workflow, a.folder, a.mode, a.friction_smoothing, a.out, a.mesh)


if __name__ == "__main__":
    main()

"""Cost of one Newton iteration of a grasp workflow's FE problem: residual, Jacobian (tissue
and contact forms), MUMPS factorisation + solve; with the NumPy Ogden kernel (default) and,
with ``--ufl``, the UFL form it replaced (its first compilation takes minutes).

    .venv/bin/python benchmarks/grasp_iteration_profile.py precision coarse
    mpirun -n 2 .venv/bin/python benchmarks/grasp_iteration_profile.py cylindrical coarse --ufl
    mpirun -n 2 .venv/bin/python benchmarks/grasp_iteration_profile.py precision default \
        --mumps icntl_35=1,cntl_7=1e-8

The scene is built by ``run_workflow`` up to the FE problem (pre-closed posture, no contact
force yet: the matrix size and pattern are what matter); the loading stage is replaced by
this measurement. Times in s, mean of 3 (factorisation: 2); CSV on stdout. The residual and
the Ogden columns recompute the kernel's stress (Newton evaluates each residual at a new state);
``mumps_factor_solve_s`` includes the analysis, ``mumps_refactor_solve_s`` is Newton's case
(the pattern's analysis kept, a new matrix factorised).
"""

from __future__ import annotations

import argparse
import time

from mpi4py import MPI
from petsc4py import PETSc

from handfe.grasp import run_workflow, scene
from handfe.parallel import rprint
from handfe.solver import MUMPS_OPTIONS, mumps_lu_ksp


def _measure(self) -> None:
    """Replaces GraspFE.solve_angles: time the pieces of a Newton iteration, then stop."""
    from dolfinx.fem import petsc as fp

    comm = self.problem.comm
    S = self.solver
    x = self.problem.w.vector.copy()
    b = x.duplicate()
    A = S.A

    def tm(f, n=3):
        comm.barrier()
        t = time.perf_counter()
        for _ in range(n):
            f()
        comm.barrier()
        return (time.perf_counter() - t) / n

    def form(i):
        def go():
            A.zeroEntries()
            fp.assemble_matrix(A, S.a[i], bcs=self.problem.bcs)
            A.assemble()
        return go

    def lu():
        # Newton's MUMPS options and any of --mumps
        ksp = mumps_lu_ksp(comm, A)
        opts = PETSc.Options()
        mumps = {**MUMPS_OPTIONS, **{f"mat_mumps_{k}": v for k, v in _measure.mumps.items()}}
        for k, v in mumps.items():
            opts[f"profile_{k}"] = v
        ksp.setOptionsPrefix("profile_")
        ksp.setFromOptions()
        return ksp

    rhs = b.duplicate()  # the residual of the pre-closed state is zero: a random right side
    rhs.setRandom()

    def factor_solve():
        ksp = lu()
        y = x.duplicate()
        ksp.solve(rhs, y)
        ksp.destroy()
        y.destroy()

    kernel = self.problem.kernel

    def forget(keep_stress=False):
        if kernel is not None:
            kernel.forget(keep_stress=keep_stress)

    def ogden(tangent):
        def go():
            forget()  # recompute: the kernel caches the last state's stress
            self.problem.update(tangent)
        return go

    def jacobian():
        # after a residual at the same state, as in Newton: the NumPy kernel reuses that call's
        # stress and eigendecomposition and computes the tangent
        forget(keep_stress=True)
        S._jacobian(None, x, A, A)

    def residual():
        forget()  # each residual of Newton is at a new state
        S._residual(None, x, b)

    r = {"residual_s": tm(residual),
         "jacobian_s": tm(jacobian),
         "tissue_form_s": tm(form(0)), "contact_form_s": tm(form(1)),
         "ogden_stress_s": tm(ogden(False)), "ogden_stress_tangent_s": tm(ogden(True))}
    S._jacobian(None, x, A, A)
    r["mumps_factor_solve_s"] = tm(factor_solve, 2)
    # as in Newton: the pattern's analysis is kept, a new Jacobian is factorised numerically
    ksp = lu()
    y = x.duplicate()
    ksp.solve(rhs, y)
    total = 0.0
    for _ in range(2):
        S._jacobian(None, x, A, A)  # a new matrix state: the next solve refactorises
        comm.barrier()
        t = time.perf_counter()
        ksp.solve(rhs, y)
        comm.barrier()
        total += time.perf_counter() - t
    r["mumps_refactor_solve_s"] = total / 2
    res = b.duplicate()
    A.mult(y, res)
    res.axpy(-1.0, rhs)
    r["mumps_relres"] = res.norm() / rhs.norm()  # of the last solve (BLR is approximate)
    res.destroy()
    ksp.destroy()
    y.destroy()
    _measure.result = r
    raise _Done


class _Done(Exception):
    pass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workflow", help="workflow name (workflows/NAME.toml) or path")
    ap.add_argument("mesh", help="mesh level: coarse, reduced, default, fine")
    ap.add_argument("--ufl", action="store_true", help="the UFL Ogden form instead of NumPy")
    ap.add_argument("--mumps", default="", metavar="K=V,...",
                    help="MUMPS options for the factorisation columns, without 'mat_mumps_', "
                         "e.g. icntl_35=1,cntl_7=1e-8 (block low-rank) or icntl_7=5 (METIS)")
    a = ap.parse_args()
    try:
        _measure.mumps = dict(kv.split("=", 1) for kv in a.mumps.split(",") if kv)
    except ValueError:
        ap.error(f"--mumps {a.mumps!r}: expected KEY=VALUE pairs separated by commas")
    comm = MPI.COMM_WORLD
    if a.ufl:
        from handfe.grasp import fe

        init = fe.GraspProblem.__init__

        def ufl_init(self, *args, **kw):
            kw["ogden_kernel"] = "ufl"
            init(self, *args, **kw)

        fe.GraspProblem.__init__ = ufl_init
    scene.GraspFE.solve_angles = _measure
    scene.GraspFE.solve_muscles = _measure
    try:
        run_workflow(a.workflow, mesh=a.mesh, progress=False, comm=comm)
    except _Done:
        pass
    r = _measure.result
    rprint("workflow,mesh,kernel,ranks," + ",".join(r) + ",mumps_options")
    rprint(f"{a.workflow},{a.mesh},{'ufl' if a.ufl else 'numpy'},{comm.size},"
           + ",".join(f"{v:.1e}" if k == "mumps_relres" else f"{v:.3f}" for k, v in r.items())
           + f",{a.mumps.replace(',', ' ')}")


if __name__ == "__main__":
    main()

"""Cost of one Newton iteration on the fingertip scene: Jacobian assembly, MUMPS symbolic +
numeric factorisation, numeric factorisation alone, triangular solve; for several sets of PETSc
options (comma-separated key=value, without prefix; "default" = the solver's defaults).

    mpirun -n 2 .venv/bin/python benchmarks/fingertip_linear_solver_profile.py default \\
        default mat_mumps_icntl_7=5 mat_mumps_icntl_35=1,mat_mumps_cntl_7=1e-8

First argument: mesh level (coarse, reduced, default, fine). The state is the plate 1 mm past
first contact, u = 0 (the matrix pattern and size are what matter). Times in s, 2 repeats.
"""

from __future__ import annotations

import sys
import time

from mpi4py import MPI

from handfe.fingertip_scene import FingertipCompression, FingertipConfig
from handfe.parallel import rprint
from handfe.solver import NewtonOptions, NewtonSolver


def main() -> None:
    comm = MPI.COMM_WORLD
    if len(sys.argv) < 3:
        rprint(__doc__)
        raise SystemExit(2)
    sc = FingertipCompression(FingertipConfig(mesh=sys.argv[1]))
    sc._set_plate(1.0)
    rprint(f"mesh {sys.argv[1]}: {sc.problem.num_dofs()} dofs, {comm.size} rank(s)")
    for spec in sys.argv[2:]:
        opts = {} if spec == "default" else dict(kv.split("=", 1) for kv in spec.split(","))
        ns = NewtonSolver(sc.problem, NewtonOptions(petsc_options=opts))
        x = ns.x
        sc.problem.w.vector.copy(x)
        ksp = ns.snes.getKSP()
        pc = ksp.getPC()
        ns._jacobian(None, x, ns.A, ns.A)
        ns._residual(None, x, ns.b)
        ksp.setOperators(ns.A)
        comm.barrier()
        t = time.perf_counter()
        pc.setUp()
        comm.barrier()
        t_first = time.perf_counter() - t
        tj = tn = 0.0
        for _ in range(2):
            comm.barrier()
            t = time.perf_counter()
            ns._jacobian(None, x, ns.A, ns.A)
            comm.barrier()
            tj += time.perf_counter() - t
            t = time.perf_counter()
            ksp.setOperators(ns.A)
            pc.setUp()
            comm.barrier()
            tn += time.perf_counter() - t
        y = x.duplicate()
        t = time.perf_counter()
        ksp.solve(ns.b, y)
        ts = time.perf_counter() - t
        r = ns.b.duplicate()
        ns.A.mult(y, r)
        r.axpy(-1.0, ns.b)
        rprint(f"{spec}: first setup {t_first:.3f} s, Jacobian {tj / 2:.3f} s, numeric factor "
               f"{tn / 2:.3f} s, solve {ts:.3f} s, relative residual {r.norm() / ns.b.norm():.1e}")
        for v in (y, r):
            v.destroy()
        del pc, ksp  # a PC handle alive at destroy() keeps its factor (handfe.solver.mumps_lu_ksp)
        ns.destroy()


if __name__ == "__main__":
    main()

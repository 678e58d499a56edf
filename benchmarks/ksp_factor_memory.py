"""Memory of repeated MUMPS LU solves: a PC handle alive at ``ksp.destroy()`` against
:func:`handfe.solver.mumps_lu_ksp`.

    .venv/bin/python benchmarks/ksp_factor_memory.py [N]

Builds the 5-point Laplacian on an N x N grid (default 200: 40,000 unknowns, 1 rank), then
for each pattern factorises and solves it six times with a fresh KSP, destroying it after
each solve, and prints the resident memory (MB) after every solve as CSV. With petsc4py 3.18
(Debian 12) the ``handle`` pattern - ``pc = ksp.getPC()`` still referenced when the KSP is
destroyed, as ``condensed_tangent`` had it until 4 Dec 2026 - keeps every LU factor (+22 MB
per solve at N = 200); ``mumps_lu_ksp`` stays flat. The patterns run in separate processes so
one's memory does not hide the other's.
"""

from __future__ import annotations

import subprocess
import sys


def _measure(pattern: str, n: int) -> None:
    from mpi4py import MPI
    from petsc4py import PETSc

    from handfe.solver import mumps_lu_ksp, resident_memory_mb

    A = PETSc.Mat().createAIJ([n * n, n * n], nnz=5, comm=MPI.COMM_SELF)
    for i in range(n * n):
        r, c = divmod(i, n)
        A.setValue(i, i, 4.0)
        for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
            if 0 <= rr < n and 0 <= cc < n:
                A.setValue(i, rr * n + cc, -1.0)
    A.assemble()
    b = A.createVecRight()
    b.set(1.0)
    x = b.duplicate()
    for k in range(6):
        if pattern == "handle":
            ksp = PETSc.KSP().create(MPI.COMM_SELF)
            ksp.setOperators(A)
            ksp.setType("preonly")
            pc = ksp.getPC()
            pc.setType("lu")
            pc.setFactorSolverType("mumps")
        else:
            ksp = mumps_lu_ksp(MPI.COMM_SELF, A)
        ksp.solve(b, x)
        ksp.destroy()  # with the "handle" pattern, pc is still referenced here
        print(f"{pattern},{k + 1},{resident_memory_mb():.0f}", flush=True)


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--pattern":
        _measure(sys.argv[2], int(sys.argv[3]))
        return
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    print("pattern,solve,rss_MB", flush=True)
    for pattern in ("handle", "mumps_lu_ksp"):
        subprocess.run([sys.executable, __file__, "--pattern", pattern, str(n)], check=True)


if __name__ == "__main__":
    main()

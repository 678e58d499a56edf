"""Compile time against assembly time of the UFL Ogden forms for gcc optimisation flags.

Each flag runs in a child process with an empty form cache (its own ``XDG_CACHE_HOME`` under
``--work``): the forms of an incompressible Taylor-Hood cube of Ogden skin are compiled (the
``handfe material`` cube, :func:`handfe.verification.cube_stress_curve`), then its Jacobian is
assembled on a unit cube of ``--n`` ^3 x 6 cells (median of ``--repeat``). One process; s; CSV
on stdout. Why the small verification meshes compile at ``-O0``
(:data:`handfe.solver.FAST_COMPILE`): docs/materials.md.

    .venv/bin/python benchmarks/compile_flags.py --flags=-O0,-O1,-O2 --png results/compile_flags.png
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = "--child"


def child(flag: str, n: int, repeat: int) -> None:
    """Compile the cube's forms with ``flag``, then time the Jacobian's assembly; prints
    ``compile_s,assembly_s``."""
    import numpy as np
    from dolfinx.fem import petsc as fem_petsc
    from mpi4py import MPI

    from handfe.materials import Ogden
    from handfe.solver import Discretisation, HyperelasticProblem
    from handfe.verification import unit_cube

    jit = {"cffi_extra_compile_args": [flag, "-g0"]}

    def problem(cells: int) -> HyperelasticProblem:
        return HyperelasticProblem(unit_cube(MPI.COMM_SELF, cells), Ogden.skin(),
                                   disc=Discretisation("taylor-hood"), incompressible=True,
                                   jit_params=jit)

    t = time.perf_counter()
    problem(1).compiled()
    compile_s = time.perf_counter() - t
    big = problem(n)
    _, a = big.compiled()  # from the cache: the same forms
    big.w.sub(0).interpolate(lambda x: np.vstack([0.1 * x[0], -0.04 * x[1], 0.02 * x[2]]))
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        A = fem_petsc.assemble_matrix(a)
        A.assemble()
        ts.append(time.perf_counter() - t)
        A.destroy()
    print(f"{compile_s:.2f},{float(np.median(ts)):.3f}")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == CHILD:
        child(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]))
        return
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flags", default="-O0,-O1,-O2",
                    help="comma-separated gcc optimisation flags (default -O0,-O1,-O2)")
    ap.add_argument("--n", type=int, default=8,
                    help="cube divisions for the assembly timing (n^3 x 6 cells; default 8)")
    ap.add_argument("--repeat", type=int, default=3, help="assemblies timed (default 3)")
    ap.add_argument("--work", type=Path, default=None,
                    help="folder for the empty form caches (default: a temporary one)")
    ap.add_argument("--png", type=Path, default=None, help="also draw the table here")
    a = ap.parse_args()
    flags = [f.strip() for f in a.flags.split(",") if f.strip()]
    if not flags or any(not f.startswith("-O") for f in flags):
        ap.error(f"--flags '{a.flags}': expected gcc flags such as -O0,-O2")
    if a.n < 1 or a.repeat < 1:
        ap.error("--n and --repeat must be >= 1")
    with tempfile.TemporaryDirectory() as tmp:
        work = a.work or Path(tmp)
        rows = []
        print("flags,compile_s,assembly_s,cells")
        for flag in flags:
            cache = work / f"cache{flag}"
            env = dict(os.environ, XDG_CACHE_HOME=str(cache))
            out = subprocess.run([sys.executable, __file__, CHILD, flag, str(a.n),
                                  str(a.repeat)], env=env, capture_output=True, text=True,
                                 check=True).stdout.strip().splitlines()[-1]
            compile_s, assembly_s = (float(x) for x in out.split(","))
            rows.append((flag, compile_s, assembly_s))
            print(f"{flag},{compile_s:.2f},{assembly_s:.3f},{6 * a.n ** 3}", flush=True)
    if a.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 4))
        for flag, c, s in rows:
            ax.loglog(c, s, "o")
            ax.annotate(flag, (c, s), textcoords="offset points", xytext=(5, 5))
        ax.set_xlabel("compile time on an empty cache (s)")
        ax.set_ylabel(f"Jacobian assembly, {6 * a.n ** 3} P2 cells (s)")
        ax.set_title("UFL Ogden forms (Taylor-Hood): gcc flags")
        ax.grid(True, which="both", alpha=0.3)
        a.png.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(a.png, dpi=120)


if __name__ == "__main__":
    main()

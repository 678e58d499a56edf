"""Fingertip scene: Newton iterations and solve time against the loose tolerance of the Newton
solves between multiplier updates (``FingertipConfig.newton_augment_atol_N``; "none" = every
solve to ``newton_atol_N``). One run per tolerance; prints CSV (rank 0).

    mpirun -n 2 .venv/bin/python benchmarks/fingertip_newton_tolerance.py --mesh reduced \\
        --tolerances none,1e-6,1e-5,1e-4,1e-3
"""

from __future__ import annotations

import argparse
import time

import handfe  # noqa: F401  (sets the BLAS thread count before petsc4py loads)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--force", type=float, default=4.0, help="plate force, N (default 4)")
    ap.add_argument("--angle", type=float, default=15.0, help="plate angle, deg (default 15)")
    ap.add_argument("--mesh", default="reduced", help="mesh level (default reduced)")
    ap.add_argument("--tolerances", default="none,1e-6,1e-5,1e-4,1e-3",
                    help="comma-separated loose tolerances, N ('none' = off)")
    a = ap.parse_args()
    from mpi4py import MPI

    from handfe.fingertip_scene import FingertipCompression, FingertipConfig

    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        print("augment_atol_N,mesh,force_N,deflection_mm,contact_area_mm2,newton_iterations,"
              "uzawa_updates,load_steps,solve_s,wall_s", flush=True)
    for tol in a.tolerances.split(","):
        t = None if tol.strip().lower() == "none" else float(tol)
        cfg = FingertipConfig(angle_deg=a.angle, mesh=a.mesh, newton_augment_atol_N=t)
        t0 = time.perf_counter()
        scene = FingertipCompression(cfg, comm=comm)
        scene.push_to_force(a.force)
        r = scene.result(time.perf_counter() - t0)
        if comm.rank == 0:
            print(f"{tol.strip()},{a.mesh},{r.force_N:.6g},{r.deflection_mm:.6f},"
                  f"{r.contact_area_mm2:.4f},{r.newton_iterations},{r.uzawa_updates},"
                  f"{r.load_steps},{r.solve_s:.2f},{r.wall_s:.2f}", flush=True)


if __name__ == "__main__":
    main()

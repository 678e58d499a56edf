"""Fingertip scene: the contact-area rules against the pad element size (docs/contact.md,
"seventh session"). One 4 N solve per size; every rule is evaluated on the same solution:

* ``clip_vertex``: the rule used before, the gap interpolated linearly over the flat triangle
  through the deformed vertices and clipped at the tolerance;
* ``nodal_vertex``: a third of each such triangle per vertex within the tolerance;
* ``clip_sub`` / ``nodal_sub``: the same on the four sub-triangles through the vertices and
  edge midpoints (``contact_metrics(area="clip" | "nodal")``; nodal is the default).

Prints CSV (rank 0), whole-fingertip areas in mm^2.

    mpirun -n 2 .venv/bin/python benchmarks/fingertip_area_rules.py \\
        --sizes 2.5:1.5,2.5:1.0,2.5:0.75,2.5:0.6,2.5:0.45 --multiplier-degree 1
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
    ap.add_argument("--sizes", default="2.5:1.5,2.5:1.0,2.5:0.75,2.5:0.6,2.5:0.45",
                    help="H:PAD element sizes (global : pad), mm, comma-separated")
    ap.add_argument("--multiplier-degree", choices=("1", "2", "u"), default="u",
                    help="normal contact multiplier degree: 1, 2 or u = the displacement's "
                         "(the scene's default)")
    a = ap.parse_args()
    import numpy as np
    from dolfinx import cpp
    from mpi4py import MPI

    from handfe.contact import (
        SUBTRIANGLES,
        _clip_patch,
        _facet_nodes,
        _nodal_patch,
        _owned_tagged_facets,
    )
    from handfe.fingertip_scene import FingertipCompression, FingertipConfig

    comm = MPI.COMM_WORLD
    deg = None if a.multiplier_degree == "u" else int(a.multiplier_degree)
    if comm.rank == 0:
        print("h_mm,h_pad_mm,multiplier_degree,dofs,deflection_mm,clip_vertex,nodal_vertex,"
              "clip_sub,nodal_sub,max_penetration_mm,newton_iterations,solve_s,wall_s",
              flush=True)
    for spec in a.sizes.split(","):
        h, pad = (float(v) for v in spec.split(":"))
        cfg = FingertipConfig(angle_deg=a.angle, h_mm=h, h_pad_mm=pad, multiplier_degree=deg)
        t0 = time.perf_counter()
        sc = FingertipCompression(cfg, comm=comm)
        sc.push_to_force(a.force)
        r = sc.result(time.perf_counter() - t0)
        c, mesh = sc.contact, sc.fm.mesh
        facets = _owned_tagged_facets(mesh, sc.fm.facet_tags, sc.fm.tags["pad"])
        nodes = cpp.mesh.entities_to_geometry(mesh._mesh, 2, facets, False)[:, :3]
        x6 = _facet_nodes(c.problem.displacement(), facets, nodes)
        t = np.asarray(c.translation.value, dtype=float)
        areas = []
        for x in (x6[:, :3], x6[:, SUBTRIANGLES].reshape(-1, 3, 3)):
            phi = c.obstacle.gap_normal(x.reshape(-1, 3), t)[0].reshape(-1, 3) - c.gap_tol_mm
            for rule in (_clip_patch, _nodal_patch):
                part = float(rule(x, phi, np.eye(3)[:2])[0].sum())
                areas.append(2.0 * comm.allreduce(part))  # half model: x 2
        if comm.rank == 0:
            print(f"{h:g},{pad:g},{a.multiplier_degree},{r.dofs},{r.deflection_mm:.5f},"
                  + ",".join(f"{v:.2f}" for v in areas)
                  + f",{r.max_penetration_mm:.4f},{r.newton_iterations},{r.solve_s:.1f},"
                  f"{r.wall_s:.1f}", flush=True)


if __name__ == "__main__":
    main()

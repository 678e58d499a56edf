"""The grasp's ``p1-p1s`` element under a pad-like compression, against Taylor-Hood.

A 12 x 12 x 5 mm block of the brief's subcutaneous Ogden set (nu = 0.499, mu0 = 0.58 kPa)
sits on a rigid "bone" (its base, a Dirichlet face of :class:`handfe.grasp.fe.BoneBC`) that
moves up by ``press`` mm and pushes the top face into a rigid ball (R = 15 mm, frictionless,
Uzawa to 0.01 mm) - a pad pressed onto an object. The stabilisation of ``p1-p1s``,
``-(beta h^2 / (2 mu)) |grad p|^2``, uses mu = mu0 by default; with contact pressures many
times mu0 it lets the tissue lose volume where the pressure varies (docs/grasp.md).
``--tangent`` sets mu to each cell's incremental shear modulus at the current state
(:meth:`GraspProblem.update_stabilisation`, lagged: updated before each step and re-solved
until it changes < 2 %); ``--pressure-factor C`` takes at least C |p| (grasp key
``solver.stabilisation_modulus = "pressure"``). Prints CSV: element, stabilisation, n,
press_mm, force_N, contact_area_mm2, mean_pressure_kPa, cell_J_min, cell_J_max, volume_ratio,
seconds; ``--curve FILE`` writes force and area after every load step, to compare the
elements' areas at equal force (the grasp's angles mode closes each digit to a force).

    .venv/bin/python benchmarks/p1p1s_compression.py --n 5,10 --press 3.0
    .venv/bin/python benchmarks/p1p1s_compression.py --n 5,10 --press 3.0 --tangent
    .venv/bin/python benchmarks/p1p1s_compression.py --n 5,10 --press 3.0 --pressure-factor 10
    .venv/bin/python benchmarks/p1p1s_compression.py --n 5,8 --element taylor-hood --steps 60
"""

from __future__ import annotations

import argparse
import sys
import time
from types import SimpleNamespace

import numpy as np
from dolfinx import mesh
from mpi4py import MPI

from handfe.contact import Sphere
from handfe.contact_problem import RigidContact
from handfe.grasp.fe import SKIN, BoneBC, GraspProblem, TwoFormNewton
from handfe.materials import Ogden

L_MM, H_MM, R_MM = 12.0, 5.0, 15.0


def press_block(n: int, press_mm: float, element: str = "p1-p1s", tangent: bool = False,
                steps: int = 20, comm=MPI.COMM_WORLD,
                curve: list[dict[str, float]] | None = None,
                pressure_factor: float = 0.0) -> dict[str, float]:
    """Press the block by ``press_mm``; the contact force (N), area (mm^2), mean pressure
    (kPa) and cell J range at the end. ``curve``, if given, gets press, force and area after
    every load step (an element's area at a given force, not only at a given press).
    ``pressure_factor`` > 0 (with ``tangent``): the stabilisation modulus is at least that
    x |p|."""
    t0 = time.perf_counter()
    msh = mesh.create_box(comm, [np.zeros(3), np.array([L_MM, L_MM, H_MM])],
                          [n, n, max(2, n * 5 // 12)], mesh.CellType.tetrahedron)
    nc = msh.topology.index_map(3).size_local
    ct = mesh.meshtags(msh, 3, np.arange(nc, dtype=np.int32), np.full(nc, SKIN, np.int32))
    base = mesh.locate_entities_boundary(msh, 2, lambda x: np.isclose(x[2], 0.0))
    top = mesh.locate_entities_boundary(msh, 2, lambda x: np.isclose(x[2], H_MM))
    f = np.concatenate([base, top]).astype(np.int32)
    v = np.concatenate([np.full(len(base), 5), np.full(len(top), 7)]).astype(np.int32)
    order = np.argsort(f)
    ft = mesh.meshtags(msh, 2, f[order], v[order])
    model = SimpleNamespace(mesh=msh, cell_tags=ct, facet_tags=ft, tags={"bone_b": 5})
    fat = Ogden.subcutaneous(nu=0.499)
    prob = GraspProblem(model, fat, fat, element=element)
    bc = BoneBC(prob, model, ["b"])
    contact = RigidContact(prob, Sphere(centre=(L_MM / 2, L_MM / 2, H_MM + R_MM), radius=R_MM),
                           ft, 7, mu=0.0, penetration_tol_mm=0.01, E_eff_MPa=0.005)
    solver = TwoFormNewton(prob, max_it=60)

    def solve(what: str) -> None:
        ok, _, why = solver.solve()
        for _ in range(20):
            if not ok:
                raise RuntimeError(f"{element} n={n}: Newton failed at {what}: {why}")
            done, _ = contact.augment(True)
            if done:
                return
            ok, _, why = solver.solve()

    for d in np.linspace(press_mm / steps, press_mm, steps):
        old = bc.ubc.x.array.copy()
        bc.set({"b": (np.eye(3), np.array([0.0, 0.0, d]))})
        bc.predict(old)
        if tangent:
            prob.update_stabilisation(pressure_factor)
        solve(f"press {d:.3f} mm")
        if curve is not None:
            m = contact.metrics()
            curve.append({"press_mm": float(d), "force_N": m.normal_force_N,
                          "contact_area_mm2": m.contact_area_mm2,
                          "mean_pressure_kPa": m.mean_pressure_kPa})
    for _ in range(10 if tangent else 0):
        change = prob.update_stabilisation(pressure_factor)
        solve("stabilisation update")
        if change < 0.02:
            break
    vol = prob.tissue_volume()
    m = contact.metrics()
    return {"force_N": m.normal_force_N, "contact_area_mm2": m.contact_area_mm2,
            "mean_pressure_kPa": m.mean_pressure_kPa,
            "cell_J_min": vol["min_cell_J"], "cell_J_max": vol["max_cell_J"],
            "volume_ratio": vol["volume_ratio"], "seconds": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", default="5,10", help="cells along the 12 mm sides, comma-separated")
    ap.add_argument("--press", type=float, default=3.0, help="bone travel into the ball (mm)")
    ap.add_argument("--element", default="p1-p1s", help="p1-p1s (default) or taylor-hood")
    ap.add_argument("--tangent", action="store_true",
                    help="p1-p1s: stabilise with the incremental shear modulus, not mu0")
    ap.add_argument("--pressure-factor", type=float, default=0.0, metavar="C",
                    help="p1-p1s: stabilise with max(incremental shear modulus, C |p|) "
                    "(implies --tangent)")
    ap.add_argument("--steps", type=int, default=20, help="load steps")
    ap.add_argument("--curve", metavar="CSV",
                    help="also write press_mm, force_N, contact_area_mm2, mean_pressure_kPa "
                    "after every load step (one block of rows per n) to this file")
    a = ap.parse_args(argv)
    comm = MPI.COMM_WORLD
    if a.pressure_factor > 0.0:
        a.tangent = True
    stab = ("-" if a.element != "p1-p1s" else f"pressure {a.pressure_factor:g}"
            if a.pressure_factor > 0.0 else "tangent" if a.tangent else "mu0")
    if comm.rank == 0:
        print("element,stabilisation,n,press_mm,force_N,contact_area_mm2,mean_pressure_kPa,"
              "cell_J_min,cell_J_max,volume_ratio,seconds")
    rows: list[str] = []
    for n in (int(x) for x in a.n.split(",")):
        curve: list[dict[str, float]] = []
        r = press_block(n, a.press, a.element, a.tangent, a.steps, curve=curve,
                        pressure_factor=a.pressure_factor)
        rows += [f"{a.element},{stab},{n},{c['press_mm']:.4f},{c['force_N']:.5f},"
                 f"{c['contact_area_mm2']:.3f},{c['mean_pressure_kPa']:.2f}" for c in curve]
        if comm.rank == 0:
            print(f"{a.element},{stab},{n},{a.press},{r['force_N']:.4f},"
                  f"{r['contact_area_mm2']:.2f},{r['mean_pressure_kPa']:.1f},"
                  f"{r['cell_J_min']:.3f},{r['cell_J_max']:.3f},{r['volume_ratio']:.4f},"
                  f"{r['seconds']:.1f}", flush=True)
    if a.curve and comm.rank == 0:
        with open(a.curve, "w") as f:
            f.write("element,stabilisation,n,press_mm,force_N,contact_area_mm2,"
                    "mean_pressure_kPa\n" + "".join(r + "\n" for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())

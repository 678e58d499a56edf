"""Can the EMG muscle torques of the pinch be held by pad forces inside the friction cone?
(rigid-link statics, no FE)

With the ball held in space and only the distal pad touching it, a digit's released joints
balance when tau_muscle + tau_ligament + J^T F = 0 (rows of J^T: a_j x (p - c_j), joint axis a_j
through centre c_j, contact point p, F the ball's force on the pad). The thumb has two released
joints (CMC, MCP flexion; its IP has no flexor among the nine muscles and is held), a finger
three with DIP = c x PIP (``dip_pip_coupling``), so two equations fix F up to one direction d
that no released joint feels (the held joints take it). The least tangential/normal ratio over
that line with |F| <= ``--max-force`` (``handfe.grasp.mechanics.friction_demand``) is the
friction the balance needs; above the grasp's mu (0.74) no held-ball balance exists at that
posture. The FE balance need not find the least-friction F: its share along d is set by the
tissue and the path, so this is a necessary condition, not a sufficient one.

Contact point: the pressure-weighted centroid of the digit's distal-pad contact facets in the
finished run folder ``R`` (``R/pressure_facets.npz``; workflow, ball centre, muscle forces and
final angles from ``R/summary.json``), carried rigidly with the distal phalanx as the angles
vary. Scanned: the two released DOFs over +-``--span`` deg (1 deg grid), keeping only postures
whose contact point stays within +-``--depth`` mm of the ball surface (compression), and the
point moved over the pad by up to +-``--roll`` mm. Ligament torques at each posture; the
tissue's own bending torque (a few % of the EMG's) is left out. ``--pip-extension-Nmm``
adds a constant extension torque at each finger PIP (what a passive joint moment or the
extensor mechanism, neither in the nine-muscle model, would supply) to ask how much of it a
balance within mu at the run's posture needs. Output: CSV on stdout.

    .venv/bin/python scripts/pad_friction_cone.py --run R [--span 10] [--roll 3] [--depth 1.5]
        [--pip-extension-Nmm 0,50,100]
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from handfe.anatomy import load_subject
from handfe.anatomy.meshing import region_code
from handfe.anatomy.skeleton import DIGIT_BONES
from handfe.grasp import load_workflow
from handfe.grasp.mechanics import (
    Kinematics,
    Ligaments,
    friction_demand,
    joint_axis_centre,
    muscle_torques,
    released_joints,
)
from handfe.grasp.outputs import load_pressure_facets
from handfe.grasp.scene import measured_pose
from handfe.kinematics import DIGITS, Pose


def contact_centroids(run: Path) -> dict[str, np.ndarray]:
    """Digit -> pressure-weighted centroid (mm, world) of its distal-pad contact facets."""
    fd, _, _ = load_pressure_facets(run / "pressure_facets.npz")
    xf, p, codes = fd["xf"], fd["p_kPa"], fd["codes"]
    area = 0.5 * np.linalg.norm(np.cross(xf[:, 1] - xf[:, 0], xf[:, 2] - xf[:, 0]), axis=1)
    w = area * p.mean(axis=1)
    out = {}
    for d in DIGITS:
        sel = (codes == region_code(d, "distal")) & (w > 0)
        if sel.any():
            out[d] = (w[sel, None] * xf[sel].mean(axis=1)).sum(axis=0) / w[sel].sum()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, required=True,
                    help="finished run folder of a ball grasp (angles mode); its workflow gives "
                         "subject, grasp, friction and the DIP-PIP coupling")
    ap.add_argument("--span", type=float, default=10.0,
                    help="+- deg about the base angles (1 deg grid)")
    ap.add_argument("--roll", type=float, default=3.0,
                    help="+- mm the force's point may move over the pad (half a patch)")
    ap.add_argument("--depth", type=float, default=1.5,
                    help="+- mm a posture may move the contact point off the ball surface")
    ap.add_argument("--max-force", type=float, default=60.0,
                    help="largest pad force, N, the held joints may add along the free direction")
    ap.add_argument("--pip-extension-Nmm", default="0",
                    help="comma-separated extension torques, N mm, added at each finger PIP "
                         "(one set of rows per value; the thumb has no PIP)")
    args = ap.parse_args()
    try:
        extensions = [float(x) for x in args.pip_extension_Nmm.split(",")]
    except ValueError:
        ap.error(f"--pip-extension-Nmm {args.pip_extension_Nmm!r}: not a list of numbers")
    for f in ("summary.json", "pressure_facets.npz"):
        if not (args.run / f).is_file():
            ap.error(f"--run {args.run}: no {f} (a finished run folder of `handfe run` with "
                     "png = true has both)")

    summ = json.loads((args.run / "summary.json").read_text())
    wf = load_workflow(summ["workflow"])
    grasp, sd = wf.grasp_spec(), wf.subject_dir()
    R_ball, mu, c = grasp.object.radius_mm, grasp.friction, wf.solver.dip_pip_coupling
    centre = np.asarray(summ["object"]["centre_world_mm"])
    vals = dict(measured_pose(wf, grasp, sd)[0].values)
    vals.update({k: v["equilibrium_deg"] for k, v in summ["joints"].items()})
    pose = Pose(vals, source="run")
    subj = load_subject(sd)
    forces = summ["muscle_forces_N"]  # the run's: its trial and muscle_scale applied
    points = contact_centroids(args.run)
    print("digit,pip_extension_Nmm,load_fraction,ratio_base_posture,least_ratio_over_scan,best_angles_deg,"
          "postures_within_mu,postures_touching")
    for d in grasp.digits:
        if d not in points:
            print(f"{d}: no distal-pad contact in {args.run}, skipped", file=sys.stderr)
            continue
        joints = released_joints((d,))
        kin = Kinematics(subj, pose, joints)
        ligs = Ligaments(kin.skel0, set(kin.skel0.bones))
        tau_m = muscle_torques(forces, joints)
        B = (np.array([[1.0, 0.0], [0.0, 1.0], [0.0, c]]) if len(joints) == 3
             else np.eye(2))  # finger: (MCP, PIP) with DIP = c PIP
        f0 = kin.skel0.bones[DIGIT_BONES[d][-1]].frame
        p_local = f0.R.T @ (points[d] - f0.o)
        grid = np.linspace(-args.span, args.span, 2 * int(args.span) + 1)
        roll = np.linspace(-args.roll, args.roll, 5)
        postures = []  # (dq, angles, ligament torques, B^T J^T and normal per rolled point)
        for dq in itertools.product(grid, grid):
            q = kin.theta0 + B @ np.asarray(dq)
            skel = kin.skeleton(q)
            f = skel.bones[DIGIT_BONES[d][-1]].frame
            p = f.R @ p_local + f.o
            if abs(np.linalg.norm(p - centre) - R_ball) > args.depth and dq != (0.0, 0.0):
                continue
            axes = [joint_axis_centre(skel, j) for j in joints]
            u = (p - centre) / np.linalg.norm(p - centre)
            t1 = np.cross(u, f.R[:, 0])
            t1 /= np.linalg.norm(t1)
            t2 = np.cross(u, t1)
            pts = []
            for r1, r2 in itertools.product(roll, repeat=2):
                v = R_ball * u + r1 * t1 + r2 * t2
                n = v / np.linalg.norm(v)
                pc = centre + R_ball * n
                pts.append((B.T @ np.array([np.cross(a, pc - ca) for a, ca in axes]), n))
            postures.append((dq, q, ligs.torques(kin.motions(skel), skel, joints), pts))
        for ext, frac in itertools.product(extensions, (0.25, 0.5, 0.5625, 0.75, 1.0)):
            tau_x = np.array([-ext if j.name.endswith("_pip") else 0.0 for j in joints])
            if ext and not tau_x.any():
                continue
            best, best_q, at0, n_ok = np.inf, None, np.inf, 0
            for dq, q, tau_l, pts in postures:
                b = -B.T @ (frac * tau_m + tau_l + tau_x)
                rmin = min(friction_demand(A, b, n, args.max_force)[0] for A, n in pts)
                n_ok += rmin <= mu
                if dq == (0.0, 0.0):
                    at0 = rmin
                if rmin < best:
                    best, best_q = rmin, q
            print(f"{d},{ext:g},{frac},{at0:.3f},{best:.3f},{' '.join(f'{x:.0f}' for x in best_q)},"
                  f"{n_ok},{len(postures)}")


if __name__ == "__main__":
    main()

"""Is the EMG muscle torque of a finger compatible with one pad force? (kinematics only, no FE)

A finger's MCP, PIP and DIP flex about (nearly) parallel axes; with its pad point p stuck on the
object, the joint motion n with Jc n = 0 (columns of Jc: a_j x (p - c_j)) keeps the pad where it
is, and no pad force resists it. The muscle torque's component along n must be taken by the
ligaments, tissue rolling under the pad or the end stops (docs/grasp.md, muscles mode). Pad
point: 5 mm palmar of the distal phalanx's palmar surface, measured glove posture of S01.

    .venv/bin/python scripts/finger_null_motion.py
"""
from pathlib import Path

import numpy as np

from handfe.anatomy import load_subject
from handfe.anatomy.skeleton import DIGIT_BONES
from handfe.emg import muscle_forces
from handfe.grasp.mechanics import Kinematics, joint_axis_centre, muscle_torques, released_joints
from handfe.kinematics import grasp_pose

sd = Path("subjects/S01")
subj = load_subject(sd)
for grasp in ("precision", "cylindrical", "spherical"):
    pose = grasp_pose(sd, grasp)
    forces = {m: f for m, (f, _) in muscle_forces(sd, grasp).items()}
    for d in ("index", "middle"):
        joints = released_joints((d,))
        kin = Kinematics(subj, pose, joints)
        skel = kin.skeleton(kin.theta0)
        tau = muscle_torques(forces, joints)
        bone = skel.bones[DIGIT_BONES[d][-1]]
        p = bone.point((0.0, 0.3, 1.0)) + 5.0 * bone.frame.R[:, 2]
        Jc = np.array([np.cross(a, p - c) for a, c in
                       (joint_axis_centre(skel, j) for j in joints)]).T  # 3 x 3
        _, sv, vt = np.linalg.svd(Jc)
        n = vt[-1]
        n = n / np.linalg.norm(n) * np.sign(n[0])
        print(f"{grasp:11s} {d:6s} tau {np.round(tau)} N mm; pad-fixed motion {np.round(n, 2)} "
              f"(sv {sv[-1]:.1e} of {sv[0]:.1e}); tau along it {tau @ n:.0f} N mm = "
              f"{abs(tau @ n) / np.linalg.norm(tau):.0%} of |tau|")

"""Rigid-bone kinematics, muscle and ligament torques of the grasp (no FE here).

Conventions: angles in degrees at interfaces, radians inside derivatives; torques in N mm about
the joint's flexion axis (the segment frame's e_x through the joint centre), positive = flexing.
Bone motion: a bone meshed in the posture ``pose0`` is moved rigidly to ``pose`` by
x -> R (x - o0) + o with (R0, o0), (R1, o) its frames, R = R1 R0^T.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass

import numpy as np

from handfe.anatomy.skeleton import JOINT_NAMES, Skeleton, build_skeleton
from handfe.anatomy.tables import CARPALS, DIGIT_BONES, tendon_shares
from handfe.errors import InputError
from handfe.kinematics import Pose, joint_table
from handfe.paths import ANATOMY_DIR

# flexion DOFs a muscle can drive (thumb IP: no flexor among the nine muscles)
RELEASED = {"thumb": ("thumb_cmc", "thumb_mcp"),
            "index": ("index_mcp", "index_pip", "index_dip")}
for _d in ("middle", "ring", "little"):
    RELEASED[_d] = tuple(j.replace("index", _d) for j in RELEASED["index"])


def moment_arms() -> dict[tuple[str, str], float]:
    """(muscle, joint) -> flexion moment arm, mm (anatomy/moment_arms.csv)."""
    path = ANATOMY_DIR / "moment_arms.csv"
    with path.open() as fh:
        rows = csv.DictReader(line for line in fh if not line.startswith("#"))
        return {(r["muscle"], r["joint"]): float(r["moment_arm_mm"]) for r in rows}


@dataclass(frozen=True)
class Joint:
    """A released flexion joint: DOF name, digit, index of the first distal bone in the digit."""

    name: str  # e.g. "index_pip"
    dof: str  # e.g. "index_pip_flexion"
    digit: str
    k: int  # position in JOINT_NAMES[digit]

    @property
    def distal_bones(self) -> tuple[str, ...]:
        return DIGIT_BONES[self.digit][self.k:]


def released_joints(digits: tuple[str, ...]) -> list[Joint]:
    out = []
    for d in digits:
        for name in RELEASED[d]:
            k = JOINT_NAMES[d].index(name)
            out.append(Joint(name, f"{name}_flexion", d, k))
    return out


def joint_axis_centre(skel: Skeleton, j: Joint) -> tuple[np.ndarray, np.ndarray]:
    """Unit flexion axis and centre (mm) of joint ``j`` in the posed skeleton."""
    bone = DIGIT_BONES[j.digit][j.k]
    return skel.segment_frames[bone].R[:, 0].copy(), np.asarray(skel.joint_centres[j.name])


class Kinematics:
    """Bone rigid motions and joint axes as functions of the released flexion angles."""

    def __init__(self, subject, pose0: Pose, joints: list[Joint]):
        self.subject, self.pose0, self.joints = subject, pose0, joints
        self.skel0 = build_skeleton(subject, pose0)
        self.theta0 = np.array([pose0[j.dof] for j in joints])
        table = joint_table()
        self.lo = np.array([table[j.dof].min for j in joints])
        self.hi = np.array([table[j.dof].max for j in joints])
        self.frames0 = {n: b.frame for n, b in self.skel0.bones.items()}

    def clamp(self, theta_deg: np.ndarray) -> np.ndarray:
        return np.clip(theta_deg, self.lo, self.hi)

    def skeleton(self, theta_deg: np.ndarray) -> Skeleton:
        vals = dict(self.pose0.values)
        for j, t in zip(self.joints, self.clamp(theta_deg), strict=True):
            vals[j.dof] = float(t)
        return build_skeleton(self.subject, Pose(vals, source="grasp"))

    def motions(self, skel: Skeleton) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Bone -> (R, t) with x_new = R x + t for points x of the meshed posture."""
        out = {}
        for n, f0 in self.frames0.items():
            f1 = skel.bones[n].frame
            R = f1.R @ f0.R.T
            out[n] = (R, f1.o - R @ f0.o)
        return out


def ligament_force_N(length_mm: float, slack_mm: float, k_N_per_mm: float,
                     eps_toe: float) -> float:
    """Tension (N) of a ligament spring: slack below its slack length, quadratic toe region up
    to strain ``eps_toe``, linear with stiffness ``k_N_per_mm`` beyond (Blankevoort 1991)."""
    eps = (length_mm - slack_mm) / slack_mm
    if eps <= 0.0:
        return 0.0
    if eps_toe <= 0.0 or eps >= eps_toe:
        return k_N_per_mm * (length_mm - slack_mm - 0.5 * eps_toe * slack_mm)
    return k_N_per_mm * slack_mm * eps * eps / (2.0 * eps_toe)


class Ligaments:
    """Ligament springs of the meshed bones, attachment points carried by the bone motions."""

    def __init__(self, skel0: Skeleton, kept_bones: set[str]):
        # carpals cut away from a partial-hand mesh still anchor their ligaments: they are fixed
        # in the hand frame (no digit flexion moves them)
        anchors = kept_bones | set(CARPALS)
        self.rows = [lg for lg in skel0.ligaments()
                     if {lg["bone_a"], lg["bone_b"]} <= anchors
                     and {lg["bone_a"], lg["bone_b"]} & kept_bones]
        self.pa0 = np.array([lg["point_a_mm"] for lg in self.rows]).reshape(-1, 3)
        self.pb0 = np.array([lg["point_b_mm"] for lg in self.rows]).reshape(-1, 3)

    def forces(self, motions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Attachment points a, b (n, 3) and force on b (n, 3) (force on a is its negative)."""
        fixed = (np.eye(3), np.zeros(3))
        motions = {**{c: fixed for c in CARPALS}, **motions}
        pa = np.array([motions[lg["bone_a"]][0] @ p + motions[lg["bone_a"]][1]
                       for lg, p in zip(self.rows, self.pa0, strict=True)]).reshape(-1, 3)
        pb = np.array([motions[lg["bone_b"]][0] @ p + motions[lg["bone_b"]][1]
                       for lg, p in zip(self.rows, self.pb0, strict=True)]).reshape(-1, 3)
        fb = np.zeros_like(pb)
        for i, lg in enumerate(self.rows):
            d = pb[i] - pa[i]
            L = float(np.linalg.norm(d))
            f = ligament_force_N(L, lg["slack_length_mm"], lg["k_N_per_mm"], lg["eps_toe"])
            fb[i] = -f * d / max(L, 1e-12)
        return pa, pb, fb

    def torques(self, motions, skel: Skeleton, joints: list[Joint]) -> np.ndarray:
        """Ligament torque about each joint (N mm) on the bones distal to it."""
        pa, pb, fb = self.forces(motions)
        out = np.zeros(len(joints))
        for i, j in enumerate(joints):
            a, c = joint_axis_centre(skel, j)
            distal = set(j.distal_bones)
            for n, lg in enumerate(self.rows):
                if lg["bone_b"] in distal:
                    out[i] += a @ np.cross(pb[n] - c, fb[n])
                if lg["bone_a"] in distal:
                    out[i] += a @ np.cross(pa[n] - c, -fb[n])
        return out


def muscle_torques(forces_N: dict[str, float], joints: list[Joint],
                   tendon_split: str = "equal") -> np.ndarray:
    """Muscle torque (N mm) about each released joint: sum of F * share * moment arm, the
    shares of ``tendon_split`` (:func:`handfe.anatomy.tables.tendon_shares`)."""
    arms, shares = moment_arms(), tendon_shares(tendon_split)
    out = np.zeros(len(joints))
    for i, j in enumerate(joints):
        for m, F in forces_N.items():
            r = arms.get((m, j.name))
            if r is None:
                continue
            share = shares.get((m, j.digit))
            if share is None:
                raise InputError(f"anatomy/insertions.csv: no insertion of {m} on {j.digit}")
            out[i] += F * share * r
    return out


def friction_demand(A: np.ndarray, b: np.ndarray, n: np.ndarray,
                    max_force_N: float = np.inf) -> tuple[float, np.ndarray]:
    """Least friction a point contact needs to balance two joint torques (rigid-link statics).

    ``A F = b`` (A: 2 x 3, the rows of J^T of two released DOFs; b: the torque, N mm, the
    contact force ``F`` (N, on the digit) must supply) leaves F free along the null direction
    d of A. Returns the smallest ``|F_t| / F_n`` (F_n = F.n > 0, ``n`` the object's outward
    unit normal) over F = F0 + s d with |F| <= ``max_force_N``, and that F; (inf, F0) if no
    such F pushes. The ratio r(s) of a line has one stationary point, s* = (f a - b e) /
    (c e - b f) (a = |P F0|^2, b = P F0 . P d, c = |P d|^2, e = F0.n, f = d.n, P = I - n n^T),
    so the minimum is there or at an end of the admissible interval.
    """
    n = np.asarray(n, float) / np.linalg.norm(n)
    F0 = np.linalg.lstsq(A, b, rcond=None)[0]
    d = np.linalg.svd(A)[2][-1]
    P = np.eye(3) - np.outer(n, n)
    pF, pd = P @ F0, P @ d
    a_, b_, c_, e_, f_ = pF @ pF, pF @ pd, pd @ pd, F0 @ n, d @ n
    # |F0 + s d| <= max_force_N: s in [lo, hi]
    if np.isfinite(max_force_N):
        q = (F0 @ d) ** 2 - (F0 @ F0 - max_force_N**2)
        if q < 0.0:
            return float("inf"), F0
        lo, hi = -F0 @ d - np.sqrt(q), -F0 @ d + np.sqrt(q)
    else:
        lo, hi = -1e12, 1e12
    cands = [lo, hi]
    den = c_ * e_ - b_ * f_
    if abs(den) > 1e-300:
        cands.append((f_ * a_ - b_ * e_) / den)
    best, F_best = float("inf"), F0
    for s in cands:
        if not lo <= s <= hi:
            continue
        F = F0 + s * d
        fn = F @ n
        if fn <= 0.0:
            continue
        r = float(np.linalg.norm(P @ F) / fn)
        if r < best:
            best, F_best = r, F
    return best, F_best


def opened_pose(pose: Pose, digits: tuple[str, ...], opening_deg: float) -> Pose:
    """``pose`` with ``opening_deg`` of flexion removed at the released joints of ``digits``
    (clamped to the joint limits)."""
    table = joint_table()
    vals = dict(pose.values)
    for j in released_joints(digits):
        lo = table[j.dof].min
        vals[j.dof] = max(lo, pose[j.dof] - opening_deg)
    return Pose(vals, source=f"{pose.source} opened by {opening_deg:g} deg")


def phalanx_bone(digit: str, phalanx: str) -> str | None:
    """The bone under a digit's skin region (``phalanx`` proximal/middle/distal); None for the
    palm (static in the pre-closing estimate)."""
    if digit not in DIGIT_BONES or not phalanx:
        return None
    bones = DIGIT_BONES[digit]
    if digit == "thumb":
        return {"proximal": bones[1], "distal": bones[2]}.get(phalanx)
    return {"proximal": bones[1], "middle": bones[2], "distal": bones[3]}.get(phalanx)


@dataclass(frozen=True)
class DigitClosing:
    """Rigid pre-closing of one digit: uniform flexion ``closing_deg`` added to its released
    joints; smallest skin-object gap before and after (mm, rigid estimate)."""

    digit: str
    closing_deg: float
    gap_before_mm: float
    gap_after_mm: float
    reaches: bool  # False: the digit's flexion arc misses the object within max_deg


class DigitArc:
    """The skin points of each digit moved rigidly with their bones while the digit's released
    flexion joints close by a common angle phi (deg, clamped at the joint limits).

    ``points`` (n, 3) mm are skin points in the posture ``pose0``; ``regions`` their (region,
    phalanx); palm points (and the thenar) do not move."""

    def __init__(self, subject, pose0: Pose, digits: tuple[str, ...], points: np.ndarray,
                 regions: list[tuple[str, str]]):
        self.joints = released_joints(digits)
        self.kin = Kinematics(subject, pose0, self.joints)
        self.points = np.asarray(points, dtype=float)
        bone_of = [phalanx_bone(r, ph) for r, ph in regions]
        self.groups: dict[str, dict[str, np.ndarray]] = {}
        for d in digits:
            idx = np.array([i for i, (r, _) in enumerate(regions)
                            if r == d and bone_of[i] is not None], dtype=int)
            self.groups[d] = {b: idx[[bone_of[i] == b for i in idx]]
                              for b in {bone_of[i] for i in idx}}

    def moved(self, digit: str, phi_deg: float) -> np.ndarray:
        """The digit's skin points after closing by ``phi_deg`` (m, 3)."""
        mask = np.array([j.digit == digit for j in self.joints])
        theta = self.kin.theta0 + np.where(mask, phi_deg, 0.0)
        mot = self.kin.motions(self.kin.skeleton(theta))
        parts = [self.points[ii] @ mot[b][0].T + mot[b][1] for b, ii in self.groups[digit].items()]
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def swept(self, digit: str, max_deg: float, step_deg: float = 2.0) -> np.ndarray:
        """The digit's skin points at phi = 0, step, ..., max_deg, stacked (k, 3)."""
        return np.concatenate([self.moved(digit, float(p))
                               for p in np.arange(0.0, max_deg + 1e-9, step_deg)])


def pre_close(arc: DigitArc, gap_fn, clearance_mm: float, max_deg: float = 60.0,
              step_deg: float = 1.0) -> dict[str, DigitClosing]:
    """Per-digit rigid estimate of the posture just short of contact: phi is the smallest common
    closing angle of the digit's released joints at which its smallest gap ``gap_fn(points) ->
    (n,)`` falls to ``clearance_mm`` (scan by ``step_deg``, then bisection to 0.01 deg). A digit
    already within the clearance keeps phi = 0; one whose arc misses the object gets the angle
    of its smallest gap (``reaches`` False)."""
    out: dict[str, DigitClosing] = {}
    for d, groups in arc.groups.items():
        if not groups:
            out[d] = DigitClosing(d, 0.0, float("nan"), float("nan"), False)
            continue

        def gap(phi: float, d: str = d) -> float:
            return float(np.min(gap_fn(arc.moved(d, phi))))

        g0 = gap(0.0)
        if g0 <= clearance_mm:
            out[d] = DigitClosing(d, 0.0, g0, g0, True)
            continue
        lo, best, gbest, hit = 0.0, 0.0, g0, None
        for phi in np.arange(step_deg, max_deg + 1e-9, step_deg):
            g = gap(float(phi))
            if g < gbest:
                best, gbest = float(phi), g
            if g <= clearance_mm:
                hit = float(phi)
                break
            lo = float(phi)
        if hit is None:
            out[d] = DigitClosing(d, best, g0, gbest, False)
            continue
        hi = hit
        while hi - lo > 0.01:
            mid = 0.5 * (lo + hi)
            if gap(mid) > clearance_mm:
                lo = mid
            else:
                hi = mid
        out[d] = DigitClosing(d, lo, g0, gap(lo), True)
    return out


def closed_pose(pose: Pose, closing: dict[str, DigitClosing]) -> Pose:
    """``pose`` with each digit's pre-closing angle added to its released joints (clamped)."""
    table = joint_table()
    vals = dict(pose.values)
    for d, c in closing.items():
        for j in released_joints((d,)):
            lim = table[j.dof]
            vals[j.dof] = min(lim.max, max(lim.min, pose[j.dof] + c.closing_deg))
    return Pose(vals, source=f"{pose.source}, pre-closed to contact")

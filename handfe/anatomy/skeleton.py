"""Forward kinematics of the hand: bone frames, bone ellipsoids, soft-tissue primitives,
ligament attachments and tendon insertions in the posed configuration.

Frames (right hand, mm): the world frame is the forearm frame. The hand frame is the world frame
rotated by the wrist (pronation about -y, then flexion about +x, then deviation about +z) and
translated by (wrist_tx, wrist_ty, wrist_tz). In the hand frame x is radial, y distal, z palmar.
Each digit segment has a frame with origin at its proximal joint centre, e_y along the segment,
e_x the flexion axis (positive rotation about e_x = flexion) and e_z palmar. MCP (and thumb CMC)
joints abduct first (about e_z, sign per digit from ``anatomy/rays.csv`` so that + is the
direction of ``anatomy/joints.csv``) and then flex about the abducted e_x. Every rotation acts
about a frame centred in the head of the proximal bone (brief S1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from handfe.anatomy.subject import Anthropometry
from handfe.anatomy.tables import (
    CARPALS,
    DIGIT_BONES,
    bones,
    insertions,
    ligaments,
    rays,
)
from handfe.errors import InputError
from handfe.kinematics import DIGITS, Pose

FINGERS_ = ("index", "middle", "ring", "little")

JOINT_GAP_MM = 1.6  # gap between a bone's end and the joint centre (cartilage / joint space)
SEGMENT_NAMES = {"thumb": ("metacarpal", "proximal", "distal"),
                 "index": ("metacarpal", "proximal", "middle", "distal")}
for _d in ("middle", "ring", "little"):
    SEGMENT_NAMES[_d] = SEGMENT_NAMES["index"]
JOINT_NAMES = {"thumb": ("thumb_cmc", "thumb_mcp", "thumb_ip"),
               "index": ("index_cmc", "index_mcp", "index_pip", "index_dip")}
for _d in ("middle", "ring", "little"):
    JOINT_NAMES[_d] = tuple(j.replace("index", _d) for j in JOINT_NAMES["index"])


def rot(axis: np.ndarray | tuple[float, float, float], angle_deg: float) -> np.ndarray:
    """Rotation matrix (right hand rule) about ``axis`` by ``angle_deg``."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    t = np.deg2rad(angle_deg)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


@dataclass(frozen=True)
class Frame:
    """Rigid frame: ``R`` (columns e_x, e_y, e_z in world coordinates) and origin ``o`` (mm)."""

    R: np.ndarray
    o: np.ndarray

    def apply(self, p_local: np.ndarray) -> np.ndarray:
        """Local coordinates (..., 3) -> world coordinates."""
        return np.asarray(p_local, dtype=float) @ self.R.T + self.o

    def inverse_apply(self, p_world: np.ndarray) -> np.ndarray:
        return (np.asarray(p_world, dtype=float) - self.o) @ self.R

    def compose(self, R_local: np.ndarray, o_local: np.ndarray) -> Frame:
        """Child frame given in this frame's coordinates."""
        return Frame(self.R @ R_local, self.apply(o_local))

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix (local -> world)."""
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.o
        return M


@dataclass(frozen=True)
class Ellipsoid:
    """Ellipsoid with centre ``c`` (world), axes = columns of ``R``, semi-axes ``s`` (mm)."""

    c: np.ndarray
    R: np.ndarray
    s: np.ndarray

    def level(self, p: np.ndarray) -> np.ndarray:
        """Scaled radius: < 1 inside, 1 on the surface, > 1 outside."""
        q = (np.atleast_2d(p) - self.c) @ self.R / self.s
        return np.linalg.norm(q, axis=1)

    def surface_points(self, n: int = 400) -> np.ndarray:
        u = _fibonacci_sphere(n)
        return (u * self.s) @ self.R.T + self.c


@dataclass(frozen=True)
class Bone:
    name: str
    digit: str  # thumb..little | hand
    segment: str  # metacarpal | proximal | middle | distal | carpal
    parent_joint: str
    frame: Frame  # segment frame (carpals: hand frame)
    centre_local: np.ndarray
    semi_axes: np.ndarray  # along e_x, e_y, e_z of the frame (mm)

    @property
    def ellipsoid(self) -> Ellipsoid:
        return Ellipsoid(self.frame.apply(self.centre_local), self.frame.R, self.semi_axes)

    def point(self, uvw: tuple[float, float, float]) -> np.ndarray:
        """World point of normalised bone coordinates (u, v, w) (see anatomy/ligaments.csv)."""
        return self.frame.apply(self.centre_local + np.asarray(uvw) * self.semi_axes)


@dataclass(frozen=True)
class Primitive:
    """A soft-tissue building block of the outer envelope (the inner envelope is the same block
    shrunk by the skin thickness). kind: "sphere" (dims = (radius,)), "ccone" (circular frustum
    along e_y: dims = (length, r0, r1)), "ellipsoid" (``dims`` = semi-axes), "cone" (elliptic
    frustum along e_y from the frame origin: dims = (length, a0, a1, aspect) with x-semi-axis a
    and z-semi-axis a*aspect), or "palm" (loft through rounded rectangles; see ``sections``)."""

    name: str
    kind: str
    frame: Frame
    dims: tuple[float, ...]
    region: str  # thumb..little | palm
    phalanx: str  # proximal | middle | distal | "" (palm)
    # (region, phalanx, point, normal): points with (p - point).normal <= 0 get this region
    split: tuple[str, str, np.ndarray, np.ndarray] | None = None
    sections: tuple = field(default=())  # palm: (frame, half extents, fillet radius) per box

    def level(self, p: np.ndarray, shrink: float = 0.0) -> np.ndarray:
        """Approximate scaled radius of points ``p`` (< 1 inside)."""
        q = self.frame.inverse_apply(np.atleast_2d(p))
        if self.kind == "ellipsoid":
            s = np.asarray(self.dims) - shrink
            return np.linalg.norm(q / s, axis=1)
        if self.kind == "sphere":
            return np.linalg.norm(q, axis=1) / (self.dims[0] - shrink)
        if self.kind == "ccone":
            L, r0, r1 = self.dims
            t = q[:, 1] / L
            r = r0 + (r1 - r0) * np.clip(t, 0, 1) - shrink
            return np.where((t < 0) | (t > 1), np.inf, np.hypot(q[:, 0], q[:, 2]) / r)
        if self.kind == "cone":
            L, a0, a1, asp = self.dims
            t = q[:, 1] / L
            a = a0 + (a1 - a0) * np.clip(t, 0, 1) - shrink
            b = (a0 + (a1 - a0) * np.clip(t, 0, 1)) * asp - shrink
            r = np.sqrt((q[:, 0] / a) ** 2 + (q[:, 2] / b) ** 2)
            out = np.where((t < 0) | (t > 1), np.inf, r)
            return out
        raise ValueError(self.kind)

    def region_phalanx(self, p: np.ndarray) -> tuple[str, str]:
        if self.split is None:
            return self.region, self.phalanx
        lo_region, lo_phalanx, point, normal = self.split
        if float(np.dot(np.asarray(p) - point, normal)) > 0:
            return self.region, self.phalanx
        return lo_region, lo_phalanx


@dataclass(frozen=True)
class Skeleton:
    """The posed hand: frames, bones, soft-tissue primitives, ligaments, insertions."""

    subject: Anthropometry
    pose: Pose
    hand_frame: Frame
    segment_frames: dict[str, Frame]  # "index_pp" -> frame of the segment holding that bone
    joint_centres: dict[str, np.ndarray]
    bones: dict[str, Bone]
    primitives: tuple[Primitive, ...]
    digit_primitives: dict[str, tuple[int, ...]]  # digit -> indices into primitives

    def bone_frames(self) -> dict[str, np.ndarray]:
        return {n: b.frame.matrix() for n, b in self.bones.items()}

    def ligaments(self) -> list[dict]:
        """Ligament springs with posed attachment points, current and slack lengths (mm)."""
        neutral = self if not self.pose.values else build_skeleton(self.subject, Pose.neutral())
        out = []
        for row in ligaments():
            pa = self.bones[row.bone_a].point(row.point_a)
            pb = self.bones[row.bone_b].point(row.point_b)
            l0 = float(np.linalg.norm(neutral.bones[row.bone_a].point(row.point_a)
                                      - neutral.bones[row.bone_b].point(row.point_b)))
            out.append({"name": row.name, "group": row.group, "bone_a": row.bone_a,
                        "bone_b": row.bone_b, "point_a_mm": pa.tolist(), "point_b_mm": pb.tolist(),
                        "length_mm": float(np.linalg.norm(pa - pb)),
                        "slack_length_mm": l0 / (1.0 + row.strain_ref),
                        "k_N_per_mm": row.k_N_per_mm, "eps_toe": row.eps_toe,
                        "source": row.source})
        return out

    def insertions(self) -> list[dict]:
        """Tendon insertions: point (mm) and unit line of action in the posed frame."""
        out = []
        for row in insertions():
            p = self.bones[row.bone].point(row.point)
            q = self.bones[row.toward_bone].point(row.toward)
            d = (q - p) / np.linalg.norm(q - p)
            out.append({"muscle": row.muscle, "digit": row.digit, "bone": row.bone,
                        "point_mm": p.tolist(), "direction": d.tolist(), "share": row.share})
        return out

    def classify(self, points: np.ndarray, digits: tuple[str, ...] | None = None,
                 tol: float = 0.06) -> tuple[list[str], list[str]]:
        """Region (thumb..little, palm) and phalanx (proximal/middle/distal, '' for palm) of
        points on (or near) the outer skin surface: the primitive whose surface the point is on.
        Points on no digit primitive (within ``tol`` in scaled radius) belong to the palm."""
        pts = np.atleast_2d(points)
        idx = [i for d in (digits or DIGITS) for i in self.digit_primitives.get(d, ())]
        if not idx:
            return ["palm"] * len(pts), [""] * len(pts)
        lev = np.stack([self.primitives[i].level(pts) for i in idx], axis=1)
        best = np.argmin(lev, axis=1)
        regions, phal = [], []
        for k, p in enumerate(pts):
            if lev[k, best[k]] > 1.0 + tol:
                regions.append("palm")
                phal.append("")
            else:
                r, ph = self.primitives[idx[best[k]]].region_phalanx(p)
                regions.append(r)
                phal.append(ph)
        return regions, phal


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)


def wrist_frame(pose: Pose) -> Frame:
    """Hand frame in the world (forearm) frame."""
    R = (rot((0, -1, 0), pose["wrist_pronation"]) @ rot((1, 0, 0), pose["wrist_flexion"])
         @ rot((0, 0, 1), pose["wrist_deviation"]))
    return Frame(R, np.array([pose["wrist_tx"], pose["wrist_ty"], pose["wrist_tz"]]))


def digit_base_frame(subject: Anthropometry, digit: str) -> Frame:
    """Neutral frame of a digit's CMC joint, in hand-frame coordinates."""
    h = subject.hand
    ray = rays()[digit]
    o = np.array([ray.cmc_frac[0] * h.hand_breadth_mm, ray.cmc_frac[1] * h.hand_length_mm,
                  ray.cmc_frac[2] * h.hand_thickness_mm])
    R = (rot((0, 0, -1), ray.spread_deg) @ rot((1, 0, 0), ray.palmar_tilt_deg)
         @ rot((0, 1, 0), -ray.axial_pronation_deg))
    return Frame(R, o)


def _widths(subject: Anthropometry, digit: str, lengths: tuple[float, ...], pad: float):
    """Outer width and height ratio at each joint of a digit (from the MCP, or thumb MCP)."""
    d = subject.digit(digit)
    ft = subject.fingertip
    tip_ratio = ft.height_mm / ft.width_mm
    phal = lengths[1:]
    s_total = sum(phal) - pad
    pos = np.concatenate([[0.0], np.cumsum(phal[:-1]), [s_total]])
    t = pos / s_total
    w = d.base_width_mm + (d.tip_width_mm - d.base_width_mm) * t
    ratio = d.height_ratio + (tip_ratio - d.height_ratio) * t
    return w, ratio


def build_skeleton(subject: Anthropometry, pose: Pose | None = None) -> Skeleton:
    """Forward kinematics: everything placed in the posed configuration (mm, world frame)."""
    pose = pose or Pose.neutral()
    table = bones()
    h = subject.hand
    HB, HL, HT = h.hand_breadth_mm, h.hand_length_mm, h.hand_thickness_mm
    t_skin = h.skin_thickness_mm
    H = wrist_frame(pose)
    seg_frames: dict[str, Frame] = {}
    joints: dict[str, np.ndarray] = {}
    bone_objs: dict[str, Bone] = {}
    prims: list[Primitive] = []
    digit_prims: dict[str, list[int]] = {d: [] for d in DIGITS}
    ft = subject.fingertip
    ex, ey, ez = np.eye(3)

    def add_prim(p: Primitive, digit: str | None) -> None:
        if digit:
            digit_prims[digit].append(len(prims))
        prims.append(p)

    for digit in DIGITS:
        d = subject.digit(digit)
        lengths = d.segment_lengths_mm
        names = DIGIT_BONES[digit]
        segs = SEGMENT_NAMES[digit]
        jn = JOINT_NAMES[digit]
        sign = rays()[digit].abduction_sign
        base = H.compose(digit_base_frame(subject, digit).R, digit_base_frame(subject, digit).o)
        tipscale = d.tip_width_mm / ft.width_mm
        pad = ft.pad_length_mm * tipscale
        w, ratio = _widths(subject, digit, lengths, pad)
        # chain of frames
        frames = []
        F = base
        joints[jn[0]] = F.o.copy()
        if digit == "thumb":
            Rab = rot(ez, sign * pose["thumb_cmc_abduction"])
            F = Frame(F.R @ Rab @ rot(ex, pose["thumb_cmc_flexion"]), F.o)
            cmc_abd_frame = Frame(base.R @ Rab, base.o)
        frames.append(F)
        for k in range(1, len(lengths)):
            o = F.apply(np.array([0.0, lengths[k - 1], 0.0]))
            joint = jn[k]
            joints[joint] = o
            if k == 1:
                Rab = rot(ez, sign * pose[f"{digit}_mcp_abduction"])
                abd_frame = Frame(F.R @ Rab, o)
                R = Rab @ rot(ex, pose[f"{digit}_mcp_flexion"])
            else:
                dof = f"{joint}_flexion"
                R = rot(ex, pose[dof])
            F = Frame(F.R @ R, o)
            frames.append(F)
        for name, F in zip(names, frames, strict=True):
            seg_frames[name] = F
        # bones
        for k, (name, seg, F) in enumerate(zip(names, segs, frames, strict=True)):
            row = table[name]
            L = lengths[k]
            bw, bh = row.width_frac * HB, row.height_frac * HB
            y0, y1 = JOINT_GAP_MM, L - JOINT_GAP_MM
            zc = 0.0
            if seg == "distal":
                bw, bh = ft.bone_width_mm * tipscale, ft.bone_height_mm * tipscale
                y1 = L - 0.35 * pad
                h_tip = w[-1] * ratio[-1]
                zc = h_tip / 2 - ft.pulp_thickness_mm * tipscale - bh / 2
                # keep >= 1 mm of subcutaneous tissue between the bone and the nail-bed skin
                zc = min(zc, -(h_tip / 2 - subject.hand.skin_thickness_mm - 1.0) + bh / 2)
            elif seg in ("proximal", "middle"):
                zc = -0.04 * w[k - 1] * ratio[k - 1]
            bone_objs[name] = Bone(name, digit, seg, row.parent_joint, F,
                                   np.array([0.0, (y0 + y1) / 2, zc]),
                                   np.array([bw / 2, (y1 - y0) / 2, bh / 2]))
        # soft-tissue primitives (outer envelope)
        phal_frames = frames[1:]
        phal_names = segs[1:]
        # cross-section semi-axes (x, z) at both ends of each phalanx segment
        ends = []
        for k, seg in enumerate(phal_names):
            asp = 0.5 * (ratio[k] + ratio[k + 1])
            if seg == "distal":  # elliptic sections where the pad makes contact
                ends.append(((w[k] / 2, w[k] / 2 * asp), (w[k + 1] / 2, w[k + 1] / 2 * asp)))
            else:  # circular elsewhere: analytic surfaces, fast and robust booleans
                r0, r1 = w[k] / 2 * (1 + asp) / 2, w[k + 1] / 2 * (1 + asp) / 2
                ends.append(((r0, r0), (r1, r1)))
        for k, (F, seg) in enumerate(zip(phal_frames, phal_names, strict=True)):
            L = lengths[k + 1] - (pad if seg == "distal" else 0.0)
            (a0, b0), (a1, b1) = ends[k]
            if seg == "distal":
                add_prim(Primitive(f"{digit}_{seg}_cone", "cone", F, (L, a0, a1, b0 / a0),
                                   digit, seg), digit)
            else:
                add_prim(Primitive(f"{digit}_{seg}_cone", "ccone", F, (L, a0, a1), digit, seg),
                         digit)
            # joint at the proximal end of this segment: covers both adjacent segment ends
            # with a 4 % margin, so that no flat end cap of a frustum is exposed
            if k == 0:
                split = ("palm", "", F.o, F.R[:, 1])
                jF = abd_frame
                jname = f"{digit}_mcp_joint"
                ax, az = a0, b0
            else:
                prev = phal_frames[k - 1]
                n = prev.R[:, 1] + F.R[:, 1]
                split = (digit, phal_names[k - 1], F.o, n / np.linalg.norm(n))
                jF = Frame(F.R, F.o)
                jname = f"{digit}_{phal_names[k - 1]}_{seg}_joint"
                (pa, pb) = ends[k - 1][1]
                ax, az = max(a0, pa), max(b0, pb, pa if seg == "distal" else 0.0)
            if seg == "distal":
                jw, jh = 1.04 * ax, 1.04 * max(az, ends[k - 1][1][0])
                add_prim(Primitive(jname, "ellipsoid", jF, (jw, jh, jh), digit, seg, split),
                         digit)
            else:
                add_prim(Primitive(jname, "sphere", jF, (1.04 * max(ax, az),), digit, seg,
                                   split), digit)
        # fingertip pad (covers the end of the distal frustum)
        F = phal_frames[-1]
        Ld = lengths[-1]
        tipF = Frame(F.R, F.apply(np.array([0.0, Ld - pad, 0.0])))
        a_end, b_end = ends[-1][1]
        add_prim(Primitive(f"{digit}_tip", "ellipsoid", tipF,
                           (1.02 * max(w[-1] / 2, a_end), pad,
                            1.02 * max(w[-1] * ratio[-1] / 2, b_end)), digit, "distal"), digit)
        if digit == "thumb":
            Fm = frames[0]
            tw = h.thenar_width_mm
            asp = d.height_ratio
            add_prim(Primitive("thumb_metacarpal_cone", "ccone", Fm,
                               (lengths[0], tw / 2 * (1 + asp) / 2, w[0] / 2 * (1 + asp) / 2),
                               "palm", ""), None)
            add_prim(Primitive("thumb_cmc_joint", "sphere", cmc_abd_frame,
                               (1.03 * tw / 2 * (1 + asp) / 2,), "palm", ""), None)
    # carpals (rigid in the hand frame)
    for name in CARPALS:
        row = table[name]
        s = HB / 87.0
        L, W, Hh = (v * s for v in row.carpal_size_mm)
        c = np.array([row.carpal_centre_frac[0] * HB, row.carpal_centre_frac[1] * HL,
                      row.carpal_centre_frac[2] * HT])
        bone_objs[name] = Bone(name, "hand", "carpal", row.parent_joint, H, c,
                               np.array([W / 2, L / 2, Hh / 2]))
    # palm: union of three boxes with rounded edges (exact offsets: inner = box shrunk by the
    # skin thickness with fillet radius reduced by it): carpus/wrist, palm, distal palm + webs
    mcp = {dg: H.inverse_apply(joints[f"{dg}_mcp"]) for dg in ("index", "middle", "ring",
                                                                 "little")}
    x_rad = mcp["index"][0] + 0.6 * subject.digit("index").base_width_mm
    x_uln = mcp["little"][0] - 0.6 * subject.digit("little").base_width_mm
    u = mcp["index"] - mcp["little"]
    u[2] = 0.0
    u /= np.linalg.norm(u)
    n_mcp = np.array([-u[1], u[0], 0.0])
    if n_mcp[1] < 0:
        n_mcp = -n_mcp
    R_mcp = np.column_stack([u, n_mcp, np.cross(u, n_mcp)])
    z_mcp = mcp["middle"][2]
    c_mcp = 0.5 * (mcp["index"] + mcp["little"])
    c_mcp[2] = z_mcp
    W_mcp = float(np.dot(mcp["index"] - mcp["little"], u)) + 1.2 * max(
        subject.digit("index").base_width_mm, subject.digit("little").base_width_mm)
    xw = 0.5 * (H.inverse_apply(joints["index_cmc"])[0] + H.inverse_apply(joints["little_cmc"])[0])
    Tw, Ww = h.wrist_thickness_mm, h.wrist_breadth_mm
    y_a1 = mcp["little"][1] + 4.0
    T_web = 2.0 * (max(subject.digit(d).base_width_mm for d in FINGERS_) / 2 * 1.0 + 6.0)
    boxes = (
        # the wrist box runs 25 mm past the wrist cut; geometry cuts it with a plane there
        ("wrist", np.eye(3), np.array([xw, (20.0 - h.forearm_stub_mm - 25.0) / 2, 0.0]),
         (Ww / 2, (20.0 + h.forearm_stub_mm + 25.0) / 2, Tw / 2)),
        ("palm", np.eye(3), np.array([(x_rad + x_uln) / 2, y_a1 / 2, 0.0]),
         ((x_rad - x_uln) / 2, y_a1 / 2, HT / 2)),
        ("web", R_mcp, c_mcp - 10.0 * n_mcp, (W_mcp / 2, 20.0, T_web / 2)),
    )
    # fillet radius 0.9 x the smallest half extent (OCC needs r < every half extent)
    sections = tuple((H.compose(R, c), half, 0.9 * min(half)) for _, R, c, half in boxes)
    prims.append(Primitive("palm", "palm", H, (), "palm", "", None, sections))
    del t_skin
    return Skeleton(subject, pose, H, seg_frames, joints, bone_objs, tuple(prims),
                    {k: tuple(v) for k, v in digit_prims.items()})


def check_bones(skel: Skeleton, min_gap_mm: float = 0.3, n: int = 600) -> None:
    """Raise InputError if two bones come closer than ``min_gap_mm`` (sampled surfaces)."""
    names = list(skel.bones)
    ells = {k: skel.bones[k].ellipsoid for k in names}
    pts = {k: ells[k].surface_points(n) for k in names}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            ea, eb = ells[a], ells[b]
            if np.linalg.norm(ea.c - eb.c) > ea.s.max() + eb.s.max() + min_gap_mm:
                continue
            grown = Ellipsoid(eb.c, eb.R, eb.s + min_gap_mm)
            if np.any(grown.level(pts[a]) < 1.0):
                raise InputError(f"pose {skel.pose.source}: bones {a} and {b} overlap "
                                 f"(or come closer than {min_gap_mm} mm)")

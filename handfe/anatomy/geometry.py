"""OpenCASCADE geometry of the posed hand, built with gmsh on the calling rank.

Outer envelope = union of the soft-tissue primitives of :mod:`handfe.anatomy.skeleton`
(elliptic frustums along the phalanges, spheroids at the joints, ellipsoidal fingertip pads, a
loft through rounded rectangles for the palm, a frustum + spheroid for the thenar). The inner
envelope is the same union with every primitive shrunk by the skin thickness, so skin =
outer - inner. Bones are ellipsoids; they are cut out of the subcutaneous tissue, leaving
bone-shaped cavities whose surfaces are tagged per bone. Nails are the part of the skin layer
over the dorsal distal phalanx. All of it is generated in the posed configuration. One OCC
``fragment`` gives a conformal model; volumes are classified by the fragment's map, not by
guessing from bounding boxes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from handfe.anatomy.skeleton import Frame, Primitive, Skeleton
from handfe.anatomy.tables import DIGIT_BONES
from handfe.errors import InputError
from handfe.kinematics import DIGITS

FINGERS = ("index", "middle", "ring", "little")
# trimmed partial hands: the proximal cut starts this far proximal to the most proximal CMC
# centre of the kept digits (then moves further if a kept metacarpal needs it)
TRIM_MARGIN_MM = 4.0


@dataclass
class OccHand:
    """Entity tags of the built gmsh model (on the rank that built it)."""

    skin: list[int]
    subcutaneous: list[int]
    nail: list[int]
    bone_surfaces: dict[str, list[int]]
    outer_surfaces: list[int]
    wrist_surfaces: list[int]
    cut_surfaces: list[int]
    bones: tuple[str, ...]
    cut_planes: list[tuple[np.ndarray, np.ndarray]]  # (point, normal pointing to the removed side)
    timings_s: dict[str, float]


def _affine(gmsh, dimtags, R: np.ndarray, o: np.ndarray) -> None:
    A = np.hstack([R, o.reshape(3, 1)])
    gmsh.model.occ.affineTransform(dimtags, A.ravel().tolist())


def _place(gmsh, dimtags, R: np.ndarray, o: np.ndarray) -> None:
    """Rigid placement by rotate + translate (keeps analytic surfaces analytic, unlike a general
    affine transform, which turns everything into B-splines)."""
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(R).as_rotvec()
    angle = float(np.linalg.norm(rv))
    if angle > 1e-14:
        ax = rv / angle
        gmsh.model.occ.rotate(dimtags, 0, 0, 0, float(ax[0]), float(ax[1]), float(ax[2]), angle)
    gmsh.model.occ.translate(dimtags, float(o[0]), float(o[1]), float(o[2]))


def _ellipsoid(gmsh, frame: Frame, c_local, s) -> tuple[int, int]:
    occ = gmsh.model.occ
    v = occ.addSphere(0, 0, 0, 1.0)
    occ.dilate([(3, v)], 0, 0, 0, float(s[0]), float(s[1]), float(s[2]))
    _place(gmsh, [(3, v)], frame.R, frame.apply(np.asarray(c_local, dtype=float)))
    return (3, v)


_P_XZ = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])  # planar (X, Y) -> section (x, z)


def _ellipse_wire(gmsh, frame: Frame, y: float, a: float, b: float) -> int:
    occ = gmsh.model.occ
    if a >= b:
        c = occ.addEllipse(0, 0, 0, a, b)
        R = _P_XZ
    else:  # gmsh needs r1 >= r2: build with the major axis along X, then map X -> z
        c = occ.addEllipse(0, 0, 0, b, a)
        R = np.array([[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    _affine(gmsh, [(1, c)], frame.R @ R, frame.apply(np.array([0.0, y, 0.0])))
    return occ.addWire([c])


def _frustum(gmsh, frame: Frame, L: float, a0: float, b0: float, a1: float, b1: float):
    occ = gmsh.model.occ
    w0 = _ellipse_wire(gmsh, frame, 0.0, a0, b0)
    w1 = _ellipse_wire(gmsh, frame, L, a1, b1)
    out = occ.addThruSections([w0, w1], makeSolid=True, makeRuled=True)
    return [dt for dt in out if dt[0] == 3]


def _primitive(gmsh, p: Primitive, shrink: float, inner: bool) -> list[tuple[int, int]]:
    occ = gmsh.model.occ
    if p.kind == "sphere":
        return [(3, occ.addSphere(*p.frame.o, p.dims[0] - shrink))]
    if p.kind == "ccone":
        L, r0, r1 = p.dims
        ax = p.frame.R[:, 1] * L
        return [(3, occ.addCone(*p.frame.o, *ax, r0 - shrink, r1 - shrink))]
    if p.kind == "ellipsoid":
        s = np.asarray(p.dims) - shrink
        return [_ellipsoid(gmsh, p.frame, (0, 0, 0), s)]
    if p.kind == "cone":
        L, a0, a1, asp = p.dims
        return _frustum(gmsh, p.frame, L, a0 - shrink, a0 * asp - shrink, a1 - shrink,
                        a1 * asp - shrink)
    if p.kind == "palm":
        out = []
        for F, half, r in p.sections:
            hx, hy, hz = (float(v) - shrink for v in half)
            b = occ.addBox(-hx, -hy, -hz, 2 * hx, 2 * hy, 2 * hz)
            occ.synchronize()
            faces = gmsh.model.getBoundary([(3, b)], combined=False, oriented=False)
            edges = sorted({abs(e) for _, e in gmsh.model.getBoundary(
                faces, combined=False, oriented=False)})
            v = occ.fillet([b], edges, [float(r) - shrink], removeVolume=True)
            v = [dt for dt in v if dt[0] == 3]
            _place(gmsh, v, F.R, F.o)
            out += v
        return out
    raise ValueError(p.kind)


def cut_planes(skel: Skeleton, digits: tuple[str, ...], trim_carpus: bool = False
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Planes that cut the palm between kept and dropped fingers (world frame): (point, normal
    towards the removed side). With ``trim_carpus`` also a plane normal to the hand's y axis,
    ``TRIM_MARGIN_MM`` proximal to the most proximal CMC centre of the kept digits: it removes
    the carpus and the wrist stub (every carpal centre lies proximal to it, so
    :func:`kept_bones` drops the carpals; it moves the plane further only if a kept metacarpal
    base needs the clearance)."""
    fingers = [d for d in FINGERS if d in digits]
    if not fingers:
        raise InputError(f"digits={','.join(digits)}: at least one of index, middle, ring, "
                         "little is needed (the palm part is chosen by the fingers)")
    i0, i1 = FINGERS.index(fingers[0]), FINGERS.index(fingers[-1])
    if fingers != list(FINGERS[i0:i1 + 1]):
        raise InputError(f"digits={','.join(digits)}: the fingers must be neighbours "
                         "(e.g. index,middle or middle,ring,little)")
    if "thumb" in digits and i0 != 0:
        raise InputError(f"digits={','.join(digits)}: the thumb needs the index finger")
    planes = []
    H = skel.hand_frame
    ez = H.R[:, 2]
    pairs = []
    if i0 > 0:
        pairs.append((FINGERS[i0 - 1], FINGERS[i0], FINGERS[i0 - 1]))
    if i1 < 3:
        pairs.append((FINGERS[i1], FINGERS[i1 + 1], FINGERS[i1 + 1]))
    for a, b, removed in pairs:
        top = 0.5 * (skel.joint_centres[f"{a}_mcp"] + skel.joint_centres[f"{b}_mcp"])
        bot = 0.5 * (skel.joint_centres[f"{a}_cmc"] + skel.joint_centres[f"{b}_cmc"])
        t = top - bot
        n = np.cross(t, ez)
        n /= np.linalg.norm(n)
        if np.dot(skel.joint_centres[f"{removed}_mcp"] - top, n) < 0:
            n = -n
        planes.append((top, n))
    if trim_carpus:
        y0 = min(H.inverse_apply(skel.joint_centres[f"{d}_cmc"])[1] for d in digits)
        planes.append((H.apply(np.array([0.0, y0 - TRIM_MARGIN_MM, 0.0])), -H.R[:, 1]))
    return planes


def kept_bones(skel: Skeleton, digits: tuple[str, ...],
               planes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[str, ...]:
    """Bones kept by a partial hand: those of the kept digits and the carpals whose centre lies
    on the kept side of the cut planes (a carpal across the plane with its centre on the
    removed side is dropped: its kept part becomes soft tissue). Each plane is then shifted (in
    place, by the smallest offset within +-30 mm) so that it clears every kept bone by the skin
    thickness + 1.5 mm (1.5 mm of subcutaneous tissue under the skin of the cut face)."""
    clear = skel.subject.hand.skin_thickness_mm + 1.5
    kept = []
    for name, b in skel.bones.items():
        if b.digit in DIGITS and b.digit not in digits:
            continue
        c = b.ellipsoid.c
        if b.segment == "carpal" and any(float(np.dot(c - p0, n)) > 0 for p0, n in planes):
            continue
        kept.append((name, b.ellipsoid))
    for k, (p0, n) in enumerate(planes):
        for off in sorted(np.arange(-30.0, 30.01, 0.25), key=abs):
            q0 = p0 + off * n
            ok = True
            for _, e in kept:
                dist = float(np.dot(e.c - q0, n))
                support = float(np.linalg.norm((e.R.T @ n) * e.s))
                if dist > -support - clear:
                    ok = False
                    break
            if ok:
                planes[k] = (q0, n)
                break
        else:
            raise InputError(f"digits={','.join(digits)}: no palm cut plane clears the bones")
    return tuple(name for name, _ in kept)


def _half_space(gmsh, skel: Skeleton, p0: np.ndarray, n: np.ndarray) -> tuple[int, int]:
    """A large box occupying {x : (x - p0).n >= 0}."""
    b = gmsh.model.occ.addBox(0, -400, -400, 400, 800, 800)
    ey = np.cross(n, skel.hand_frame.R[:, 2])
    ey /= np.linalg.norm(ey)
    _place(gmsh, [(3, b)], np.column_stack([n, ey, np.cross(n, ey)]), p0)
    return (3, b)


def _envelope(gmsh, skel: Skeleton, groups: list[list[Primitive]], shrink: float,
              planes: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[int, int]]:
    """Union of the primitives (fused group by group: one group per digit, then the palm)."""
    occ = gmsh.model.occ
    parts = []
    for prims in groups:
        vols = []
        for p in prims:
            vols += _primitive(gmsh, p, shrink, inner=shrink > 0)
        if len(vols) > 1:
            vols, _ = occ.fuse(vols[:1], vols[1:])
        parts += vols
    v, _ = occ.fuse(parts[-1:], parts[:-1])
    if planes:
        boxes = [_half_space(gmsh, skel, p0 - shrink * n, n) for p0, n in planes]
        v, _ = occ.cut(v, boxes)
    if len(v) != 1:
        raise InputError(f"geometry failed: the {'inner' if shrink else 'outer'} envelope has "
                         f"{len(v)} disconnected parts (a digit detached from the palm?)")
    return v


def build_occ(gmsh, skel: Skeleton, digits: tuple[str, ...], trim_carpus: bool = False
              ) -> OccHand:
    """Build the OCC model of the selected digits (+ the palm part carrying them; with
    ``trim_carpus`` (partial hands only) without the carpus and the wrist stub).

    No boolean touches the bones: the subcutaneous volume is made from the inner envelope's
    shell with one hole per bone shell, and the skin from the outer shell with the inner shell
    as hole (the skin also covers the wrist and palm-cut faces). Only the nails need a boolean
    (a fragment of the skin volume with one box per distal phalanx)."""
    occ = gmsh.model.occ
    t = skel.subject.hand.skin_thickness_mm
    full = tuple(d for d in DIGITS if d in digits) == DIGITS
    planes = [] if full else cut_planes(skel, digits, trim_carpus)
    bones = kept_bones(skel, digits, planes)  # may move the planes clear of carpal bones
    groups = []
    for d in DIGITS:
        if d in digits:
            groups.append([skel.primitives[i] for i in skel.digit_primitives[d]])
            if d == "thumb":
                groups[-1] += [p for p in skel.primitives if p.name in (
                    "thumb_metacarpal_cone", "thumb_cmc_joint")]
    groups.append([p for p in skel.primitives if p.kind == "palm"])
    occ.synchronize()
    tm = {}
    t0 = time.perf_counter()
    H = skel.hand_frame
    y_wrist = -skel.subject.hand.forearm_stub_mm
    wrist_plane = (H.apply(np.array([0.0, y_wrist, 0.0])), -H.R[:, 1])
    outer_v = _envelope(gmsh, skel, groups, 0.0, planes + [wrist_plane])
    tm["outer_envelope"] = time.perf_counter() - t0
    inner_v = _envelope(gmsh, skel, groups, t, planes + [wrist_plane])
    tm["inner_envelope"] = time.perf_counter() - t0 - tm["outer_envelope"]
    occ.synchronize()
    vol_outer = occ.getMass(*outer_v[0])
    vol_inner = occ.getMass(*inner_v[0])
    bone_vols = {n: _ellipsoid(gmsh, skel.bones[n].frame, skel.bones[n].centre_local,
                               skel.bones[n].semi_axes) for n in bones}
    occ.synchronize()

    def shell(v: int) -> list[int]:
        return [abs(s) for _, s in gmsh.model.getBoundary([(3, v)], combined=False,
                                                          oriented=False)]

    outer_s = shell(outer_v[0][1])
    inner_s = shell(inner_v[0][1])
    bone_surfaces = {n: shell(v[1]) for n, v in bone_vols.items()}
    occ.remove(outer_v + inner_v + list(bone_vols.values()), recursive=False)
    # gmsh 4.8's OCC addSurfaceLoop returns -1 for an automatic tag: give explicit tags
    l_out = occ.addSurfaceLoop(outer_s, 900001)
    l_in = occ.addSurfaceLoop(inner_s, 900002)
    l_b = [occ.addSurfaceLoop(bone_surfaces[n], 900003 + k) for k, n in enumerate(bones)]
    skin_v = occ.addVolume([l_out, l_in])
    sub_v = occ.addVolume([l_in] + l_b)
    occ.synchronize()
    skin, sub, nail = [skin_v], [sub_v], []
    tissue = skin + sub + nail
    ext = {abs(s) for _, s in gmsh.model.getBoundary([(3, v) for v in tissue], combined=True,
                                                     oriented=False)}
    # bone faces may have been renumbered by the fragment: find them again on the boundary
    bone_faces = {n: [] for n in bones}
    for s in sorted(ext):
        c = np.array(occ.getCenterOfMass(2, s))
        for n in bones:
            e = skel.bones[n].ellipsoid
            if np.linalg.norm(c - e.c) < 0.05 * float(e.s.min()):
                bone_faces[n].append(s)
    # a closed ellipsoid face has its centre of mass at the ellipsoid centre
    missing = [n for n, ss in bone_faces.items() if len(ss) != 1]
    if missing:
        raise InputError(f"geometry failed: bone surface(s) of {missing} not found {bone_faces}")
    bone_set = {ss[0] for ss in bone_faces.values()}
    wrist, cut_s, outer = [], [], []
    for s in sorted(ext - bone_set):
        c = np.array(occ.getCenterOfMass(2, s))
        if abs(H.inverse_apply(c)[1] - y_wrist) < 1e-3 and _is_planar(gmsh, s, H.R[:, 1]):
            wrist.append(s)
        elif any(abs(np.dot(c - p0, n)) < 1e-3 and _is_planar(gmsh, s, n) for p0, n in planes):
            cut_s.append(s)
        else:
            outer.append(s)
    if not skin or not sub:
        raise InputError("geometry failed: skin or subcutaneous volume missing")
    # volume bookkeeping catches a bone poking out of the subcutaneous tissue or two
    # intersecting bones (the shells would overlap and the volumes would not add up)
    v_bones = sum(4.0 / 3.0 * np.pi * np.prod(skel.bones[n].semi_axes) for n in bones)
    v_sub = sum(occ.getMass(3, v) for v in sub)
    v_skin = sum(occ.getMass(3, v) for v in skin)
    if (abs(v_sub - (vol_inner - v_bones)) > 2e-3 * vol_inner
            or abs(v_skin - (vol_outer - vol_inner)) > 2e-3 * vol_outer):
        raise InputError(f"pose {skel.pose.source}: inconsistent volumes (a bone sticks out of "
                         "the subcutaneous tissue or two bones intersect)")
    tm["occ_total"] = time.perf_counter() - t0
    return OccHand(skin, sub, nail, bone_faces, outer, wrist, cut_s, bones, planes, tm)


def nail_boxes(skel: Skeleton, digits: tuple[str, ...]) -> list[tuple[Frame, np.ndarray,
                                                                       np.ndarray]]:
    """Nail regions: boxes (frame of the distal segment, lower and upper corner in mm) over the
    dorsal distal phalanx; skin tetrahedra whose centroid lies inside are nail. The box stays
    0.4 mm clear of the bone, so only skin (never bone-adjacent tissue) becomes nail."""
    out = []
    for d in digits:
        F = skel.segment_frames[DIGIT_BONES[d][-1]]
        Ld = skel.subject.digit(d).segment_lengths_mm[-1]
        tip = [p for p in skel.primitives if p.name == f"{d}_tip"][0]
        a, _, c = tip.dims
        bone = skel.bones[DIGIT_BONES[d][-1]]
        z_top = bone.centre_local[2] - bone.semi_axes[2] - 0.4
        out.append((F, np.array([-0.75 * a, 0.35 * Ld, -c - 4.0]),
                    np.array([0.75 * a, Ld + 4.0, z_top])))
    return out


def in_nail(points: np.ndarray, boxes) -> np.ndarray:
    """Boolean mask: points (n, 3) inside any nail box."""
    pts = np.atleast_2d(points)
    mask = np.zeros(len(pts), dtype=bool)
    for F, lo, hi in boxes:
        q = F.inverse_apply(pts)
        mask |= np.all((q >= lo) & (q <= hi), axis=1)
    return mask


def _is_planar(gmsh, s: int, n: np.ndarray) -> bool:
    """True if surface ``s`` has the normal +-n at several parametric points (a plane)."""
    lo, hi = gmsh.model.getParametrizationBounds(2, s)
    uv = []
    for a, b in ((0.5, 0.5), (0.25, 0.3), (0.7, 0.6)):
        uv += [lo[0] + a * (hi[0] - lo[0]), lo[1] + b * (hi[1] - lo[1])]
    nn = np.array(gmsh.model.getNormal(s, uv)).reshape(-1, 3)
    return bool(np.all(np.abs(np.abs(nn @ n) - 1.0) < 1e-6))

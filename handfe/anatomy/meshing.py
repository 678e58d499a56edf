"""Tetrahedral meshing of the posed hand with gmsh (rank 0) and conversion to dolfinx.

Tags (values of the dolfinx meshtags; names in ``HandModel.tags``):
  cells:  1 skin, 2 subcutaneous, 3 nail
  facets: 90 wrist cut face (absent for a trimmed partial hand, ``skip_far``), 91 palm cut
          faces (partial hands: between kept and dropped rays, and with ``skip_far`` the cut
          through the carpus), 201.. one per bone surface
          (order of anatomy/bones.csv), and the outer skin surface split by region and phalanx:
          100 + 10 * region + phalanx with region thumb 1, index 2, middle 3, ring 4, little 5,
          palm 6 and phalanx proximal 1, middle 2, distal 3 (0 for the palm), e.g. 123 =
          skin of the index distal phalanx (``skin_index_distal``), 160 = ``skin_palm``.
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from mpi4py import MPI

from handfe.anatomy.geometry import FINGERS, build_occ, in_nail, nail_boxes
from handfe.anatomy.skeleton import Skeleton, build_skeleton, check_bones
from handfe.anatomy.subject import Anthropometry
from handfe.anatomy.tables import bones as bone_table
from handfe.errors import InputError
from handfe.gmshutil import ensure_gmsh, release_gmsh  # noqa: F401 (re-exported)
from handfe.kinematics import DIGITS, Pose
from handfe.paths import ANATOMY_DIR

LEVELS = {  # mm: global size, size on the fingertip pads, size on the palm, size far from the
    # kept digits of a partial hand (proximal palm, carpus, wrist)
    "coarse": {"h": 4.7, "h_pad": 3.0, "h_palm": 4.7, "h_far": 5.0},
    "reduced": {"h": 3.0, "h_pad": 2.0, "h_palm": 3.0, "h_far": 5.0},
    "default": {"h": 2.0, "h_pad": 1.0, "h_palm": 1.6, "h_far": 4.0},
    "fine": {"h": 1.4, "h_pad": 0.6, "h_palm": 1.1, "h_far": 2.8},
}
# whole-hand cell counts of S01 (neutral pose, `handfe anatomy --mesh LEVEL`), the basis of the
# saving reported for partial hands; fine: default scaled by (2.0 / 1.4)^3, not measured
WHOLE_HAND_CELLS_S01 = {"coarse": 42403, "reduced": 105868, "default": 368729,
                        "fine": 1075000}
S01_HAND_BOX_MM3 = 189.0 * 87.0 * 33.0
FAR_TRANSITION_MM = 10.0  # partial hands: distance over which the size grows from h to h_far
FINE_PHALANGES = ("middle", "distal")  # partial hands: kept at h (the pads at h_pad)
CELL_TAGS = {"skin": 1, "subcutaneous": 2, "nail": 3}
REGIONS = ("thumb", "index", "middle", "ring", "little", "palm")
PHALANGES = ("proximal", "middle", "distal")
SKIN_OUTER_GMSH = 100
#: what a cached meshing failure's message carries after the original error
CACHED_FAILURE = " (cached failure"
WRIST_TAG, CUT_TAG = 90, 91
BONE_TAG0 = 201
EXTRA_OPTIMIZE: tuple[str, ...] = ()
ALGORITHM_3D = 10  # HXT (gmsh's Netgen optimiser is not compiled into Debian's gmsh 4.8)


def region_code(region: str, phalanx: str) -> int:
    return 100 + 10 * (REGIONS.index(region) + 1) + (PHALANGES.index(phalanx) + 1 if phalanx
                                                       else 0)


def tag_names(digits: tuple[str, ...]) -> tuple[dict[str, int], dict[str, tuple[int, ...]]]:
    """Tag names -> ids and groups of ids (e.g. "index" -> all index skin facets)."""
    tags = {"skin": 1, "subcutaneous": 2, "nail": 3, "wrist": WRIST_TAG, "palm_cut": CUT_TAG}
    groups: dict[str, list[int]] = {r: [] for r in REGIONS}
    groups.update({p: [] for p in PHALANGES})
    groups["skin_outer"] = []
    for d in digits:
        for p in (("proximal", "distal") if d == "thumb" else PHALANGES):
            code = region_code(d, p)
            tags[f"skin_{d}_{p}"] = code
            groups[d].append(code)
            groups[p].append(code)
            groups["skin_outer"].append(code)
    tags["skin_palm"] = region_code("palm", "")
    groups["palm"].append(tags["skin_palm"])
    groups["skin_outer"].append(tags["skin_palm"])
    for k, name in enumerate(bone_table()):
        tags[f"bone_{name}"] = BONE_TAG0 + k
    groups["bones"] = [v for k, v in tags.items() if k.startswith("bone_")]
    return tags, {k: tuple(v) for k, v in groups.items() if v}


@dataclass
class SurfaceData:
    """Outer skin triangles (rank 0): points (n, 3) mm, triangles (m, 3), region code per tri."""

    points: np.ndarray
    triangles: np.ndarray
    codes: np.ndarray


@dataclass
class HandModel:
    """A meshed, posed hand. ``mesh``/``cell_tags``/``facet_tags`` are dolfinx objects
    (distributed on ``comm``); ``tags`` maps names to tag values and ``groups`` names to tuples
    of facet tag values (use ``ds(model.groups["index"])``). Geometry data (bone frames,
    ligaments, insertions) are in the posed world frame, mm."""

    mesh: object
    cell_tags: object
    facet_tags: object
    tags: dict[str, int]
    groups: dict[str, tuple[int, ...]]
    skeleton: Skeleton | None  # None for imported surfaces
    digits: tuple[str, ...]
    level: str
    quality: dict = field(default_factory=dict)
    surface: SurfaceData | None = None  # rank 0 only

    @property
    def bone_frames(self) -> dict[str, np.ndarray]:
        return self.skeleton.bone_frames() if self.skeleton is not None else {}

    @property
    def bones(self) -> tuple[str, ...]:
        return tuple(self.quality.get("bones", ()))

    @property
    def ligaments(self) -> list[dict]:
        if self.skeleton is None:
            return []
        kept = set(self.bones)
        return [lg for lg in self.skeleton.ligaments()
                if lg["bone_a"] in kept and lg["bone_b"] in kept]

    @property
    def insertions(self) -> list[dict]:
        if self.skeleton is None:
            return []
        kept = set(self.bones)
        return [i for i in self.skeleton.insertions() if i["bone"] in kept]


def parse_digits(digits: str | tuple[str, ...] | list[str] | None) -> tuple[str, ...]:
    if digits is None:
        return DIGITS
    items = [d.strip() for d in digits.split(",")] if isinstance(digits, str) else list(digits)
    items = [d for d in items if d]
    for d in items:
        if d not in DIGITS:
            raise InputError(f"unknown digit '{d}' (choose from {', '.join(DIGITS)})")
    if not items:
        raise InputError("digits: empty selection")
    return tuple(d for d in DIGITS if d in items)


def _ball(gmsh, c: np.ndarray, radius: float, v_in: float, v_out: float,
          thickness: float) -> int:
    fld = gmsh.model.mesh.field
    f = fld.add("Ball")
    fld.setNumber(f, "XCenter", float(c[0]))
    fld.setNumber(f, "YCenter", float(c[1]))
    fld.setNumber(f, "ZCenter", float(c[2]))
    fld.setNumber(f, "Radius", float(radius))
    fld.setNumber(f, "Thickness", float(thickness))
    fld.setNumber(f, "VIn", float(v_in))
    fld.setNumber(f, "VOut", float(v_out))
    return f


def digit_balls(skel: Skeleton, digits: tuple[str, ...],
                phalanges: tuple[str, ...] = PHALANGES, mcp: bool = True
                ) -> list[tuple[np.ndarray, float]]:
    """Balls (centre, radius; mm, world frame) covering the soft tissue of the given digits'
    phalanges and joints (the primitives of ``skel.digit_primitives`` whose phalanx is in
    ``phalanges``; a joint belongs to its distal segment; ``mcp``: always the MCP joint);
    long frustums are covered by several balls."""
    out = []
    for d in digits:
        for i in skel.digit_primitives[d]:
            p = skel.primitives[i]
            if p.phalanx not in phalanges and not (mcp and p.name == f"{d}_mcp_joint"):
                continue
            if p.kind in ("cone", "ccone"):
                L = p.dims[0]
                r = max(p.dims[1:3]) * (max(1.0, p.dims[3]) if p.kind == "cone" else 1.0)
                n = max(1, int(np.ceil(L / (2.0 * r))))
                for k in range(n):
                    c = p.frame.apply(np.array([0.0, (k + 0.5) * L / n, 0.0]))
                    out.append((c, float(np.hypot(0.5 * L / n, r)) + 1.0))
            elif p.kind == "sphere":
                out.append((p.frame.o, float(p.dims[0]) + 1.0))
            else:  # ellipsoid
                out.append((p.frame.o, float(max(p.dims)) + 1.0))
    return out


def _size_fields(gmsh, skel: Skeleton, digits: tuple[str, ...], lv: dict,
                 palm_contact: bool, far: bool) -> None:
    """Background mesh size: ``h_pad`` on the kept fingertip pads, ``h_palm`` on the palm
    (if it takes part in contact), ``h`` elsewhere; with ``far``, ``h`` only on the kept
    digits' middle and distal segments and MCP joints, (h + h_far) / 2 on their proximal
    phalanges, growing over ``FAR_TRANSITION_MM`` to ``h_far`` in the rest (palm, thenar)."""
    h_out = lv["h_far"] if far else lv["h"]
    ids = []
    for d in digits:
        tip = [p for p in skel.primitives if p.name == f"{d}_tip"][0]
        c = tip.frame.apply(np.array([0.0, 0.0, 0.5 * tip.dims[2]]))
        # grows from h_pad to h over 6 mm (the same gradient when the far field is coarser)
        t = 6.0 * (h_out - lv["h_pad"]) / max(lv["h"] - lv["h_pad"], 1e-9)
        ids.append(_ball(gmsh, c, 1.4 * tip.dims[1], lv["h_pad"], h_out, t))
    if far:
        for c, r in digit_balls(skel, digits, FINE_PHALANGES):
            ids.append(_ball(gmsh, c, r, lv["h"], lv["h_far"], FAR_TRANSITION_MM))
        # proximal phalanges in between: a thin subcutaneous layer under h_far makes slivers
        h_mid = 0.5 * (lv["h"] + lv["h_far"])
        for c, r in digit_balls(skel, digits, ("proximal",), mcp=False):
            ids.append(_ball(gmsh, c, r, h_mid, lv["h_far"], FAR_TRANSITION_MM))
    if palm_contact:
        H = skel.hand_frame
        ht = skel.subject.hand.hand_thickness_mm
        mcp = np.mean([H.inverse_apply(skel.joint_centres[f"{f}_mcp"]) for f in FINGERS
                       if f in digits], axis=0)
        c = H.apply(np.array([mcp[0], 0.55 * mcp[1], 0.5 * ht]))
        ids.append(_ball(gmsh, c, 0.4 * mcp[1], lv["h_palm"], h_out, 10.0))
    fld = gmsh.model.mesh.field
    m = fld.add("Min")
    fld.setNumbers(m, "FieldsList", ids)
    fld.setAsBackgroundMesh(m)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeMax", h_out)
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.5 * lv["h_pad"])


def _tet_quality(X: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, float]:
    """Radius-ratio quality (3 r_in / r_circ, 1 = regular) per tet and the smallest dihedral
    angle (degrees) over all tets."""
    P = X[tets]
    a, b, c, d = P[:, 0], P[:, 1], P[:, 2], P[:, 3]
    vol = np.abs(np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))) / 6.0
    faces = [(b, c, d), (a, c, d), (a, b, d), (a, b, c)]
    normals = [np.cross(q - p, r - p) for p, q, r in faces]
    areas = [0.5 * np.linalg.norm(n, axis=1) for n in normals]
    r_in = 3.0 * vol / np.sum(areas, axis=0)
    # circumradius
    ba, ca, da = b - a, c - a, d - a
    num = (np.einsum("ij,ij->i", ba, ba)[:, None] * np.cross(ca, da)
           + np.einsum("ij,ij->i", ca, ca)[:, None] * np.cross(da, ba)
           + np.einsum("ij,ij->i", da, da)[:, None] * np.cross(ba, ca))
    r_c = np.linalg.norm(num, axis=1) / (12.0 * vol)
    q = 3.0 * r_in / r_c
    # dihedral angles at the 6 edges: angle between the two faces sharing the edge
    verts = [a, b, c, d]
    min_dih = 180.0
    for i in range(4):
        for j in range(i + 1, 4):
            k, l = [m for m in range(4) if m not in (i, j)]
            e = verts[j] - verts[i]
            e = e / np.linalg.norm(e, axis=1)[:, None]
            u = verts[k] - verts[i]
            v = verts[l] - verts[i]
            u = u - np.einsum("ij,ij->i", u, e)[:, None] * e
            v = v - np.einsum("ij,ij->i", v, e)[:, None] * e
            cosang = np.einsum("ij,ij->i", u, v) / (np.linalg.norm(u, axis=1)
                                                    * np.linalg.norm(v, axis=1))
            ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
            min_dih = min(min_dih, float(ang.min()))
    return q, min_dih


def _mesh_rank0(gmsh, skel: Skeleton, digits: tuple[str, ...], level: str,
                skip_far: bool = False) -> dict:
    """Build geometry, mesh and physical groups in the current gmsh model; return the
    quality report and the outer surface for rendering."""
    t0 = time.perf_counter()
    occ_hand = build_occ(gmsh, skel, digits, trim_carpus=skip_far)
    model = gmsh.model
    model.addPhysicalGroup(3, occ_hand.skin, CELL_TAGS["skin"])
    model.setPhysicalName(3, CELL_TAGS["skin"], "skin")
    model.addPhysicalGroup(3, occ_hand.subcutaneous, CELL_TAGS["subcutaneous"])
    model.setPhysicalName(3, CELL_TAGS["subcutaneous"], "subcutaneous")
    model.addPhysicalGroup(2, occ_hand.outer_surfaces, SKIN_OUTER_GMSH)
    model.setPhysicalName(2, SKIN_OUTER_GMSH, "skin_outer")
    model.addPhysicalGroup(2, occ_hand.wrist_surfaces, WRIST_TAG)
    model.setPhysicalName(2, WRIST_TAG, "wrist")
    if occ_hand.cut_surfaces:
        model.addPhysicalGroup(2, occ_hand.cut_surfaces, CUT_TAG)
        model.setPhysicalName(2, CUT_TAG, "palm_cut")
    order = list(bone_table())
    for name, surfs in occ_hand.bone_surfaces.items():
        tag = BONE_TAG0 + order.index(name)
        model.addPhysicalGroup(2, surfs, tag)
        model.setPhysicalName(2, tag, f"bone_{name}")
    lv = dict(LEVELS[level])
    _size_fields(gmsh, skel, digits, lv, palm_contact=not skip_far, far=skip_far)
    t1 = time.perf_counter()
    gmsh.option.setNumber("Mesh.Optimize", 1)
    gmsh.option.setNumber("Mesh.Algorithm3D", ALGORITHM_3D)
    try:
        model.mesh.generate(3)
        if len(model.mesh.getElementsByType(4)[0]) == 0:  # HXT failures return no tets
            raise RuntimeError("gmsh returned an empty volume mesh")
    except Exception:
        if not skip_far or lv["h_far"] <= lv["h"]:
            raise
        # the coarse far-field surface mesh can make the skin's outer and inner triangles
        # intersect (a 1.2 mm layer under 5 mm triangles at tight curvature): retry at h
        model.mesh.clear()
        lv["h_far"] = lv["h"]
        _size_fields(gmsh, skel, digits, lv, palm_contact=False, far=True)
        model.mesh.generate(3)
    for method in EXTRA_OPTIMIZE:
        model.mesh.optimize(method)
    t2 = time.perf_counter()
    # --- quality report from the gmsh mesh
    node_tags, coords, _ = model.mesh.getNodes()
    if len(node_tags) == 0:
        raise RuntimeError("gmsh returned an empty mesh")
    X = np.zeros((int(node_tags.max()) + 1, 3))
    X[node_tags] = coords.reshape(-1, 3)
    boxes = nail_boxes(skel, digits)
    vols, tets_all = {}, []
    for name, ents in (("skin", occ_hand.skin), ("subcutaneous", occ_hand.subcutaneous)):
        v_sum, v_nail = 0.0, 0.0
        for e in ents:
            _, _, ntags = model.mesh.getElements(3, e)
            tets = ntags[0].reshape(-1, 4).astype(np.int64)
            tets_all.append(tets)
            P = X[tets]
            v = np.abs(np.einsum("ij,ij->i", P[:, 1] - P[:, 0],
                                 np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]))) / 6.0
            if name == "skin":
                nail = in_nail(P.mean(axis=1), boxes)
                v_nail += float(v[nail].sum())
                v_sum += float(v[~nail].sum())
            else:
                v_sum += float(v.sum())
        vols[name] = v_sum
        if name == "skin":
            vols["nail"] = v_nail
    tets = np.concatenate(tets_all)
    q, min_dih = _tet_quality(X, tets)
    bone_vol = sum(4.0 / 3.0 * np.pi * np.prod(skel.bones[n].semi_axes) for n in occ_hand.bones)
    tris, regions, codes = _outer_triangles(model, occ_hand, X, skel, digits)
    area = 0.5 * np.linalg.norm(np.cross(X[tris[:, 1]] - X[tris[:, 0]],
                                         X[tris[:, 2]] - X[tris[:, 0]]), axis=1)
    area_region = {r: float(area[[reg == r for reg in regions]].sum()) for r in REGIONS}
    area_code = {int(c): float(area[codes == c].sum()) for c in np.unique(codes)}
    thick = _skin_thickness(gmsh, skel, occ_hand, X, tris, digits)
    used = np.unique(np.concatenate([tets.ravel(), tris.ravel()]))
    surf = SurfaceData(X[used], np.searchsorted(used, tris), codes)
    quality = {
        "level": level, "digits": list(digits), "pose": skel.pose.source,
        "mesh_sizes_mm": lv,
        "cells": int(len(tets)), "vertices": int(len(node_tags)),
        "quality_measure": "radius ratio 3*r_in/r_circ (1 = regular tetrahedron)",
        "min_quality": float(q.min()), "mean_quality": float(q.mean()),
        "cells_quality_below_0.1": int((q < 0.1).sum()),
        "min_dihedral_angle_deg": min_dih,
        "volume_mm3": {k: float(v) for k, v in vols.items()},
        "bone_volume_mm3": float(bone_vol),
        "hand_volume_cm3": float((sum(vols.values()) + bone_vol) / 1000.0),
        "skin_area_mm2": area_region,
        "skin_area_by_tag_mm2": area_code,
        "skin_thickness_mm": thick,
        "bones": list(occ_hand.bones),
        "skipped": skipped_report(skel, digits, level, occ_hand.bones, int(len(tets)), skip_far,
                                  lv["h_far"]),
        "timings_s": {**{k: round(v, 2) for k, v in occ_hand.timings_s.items()},
                      "mesh_generate": round(t2 - t1, 2)},
        "meshing_time_s": round(t2 - t0, 2),
    }
    return {"quality": quality, "surface": surf}


def _outer_triangles(model, occ_hand, X: np.ndarray, skel: Skeleton, digits: tuple[str, ...]
                     ) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Outer skin triangles (gmsh node tags), their region and region code."""
    tris = []
    for s in occ_hand.outer_surfaces:
        _, _, ntags = model.mesh.getElements(2, s)
        tris.append(ntags[0].reshape(-1, 3).astype(np.int64))
    tris = np.concatenate(tris)
    regions, phal = skel.classify(X[tris].mean(axis=1), digits)
    codes = np.array([region_code(r, p) for r, p in zip(regions, phal, strict=True)])
    return tris, regions, codes


def skin_surface(subject: Anthropometry, pose: Pose, *, digits: str | tuple[str, ...] | None
                 = None, level: str = "coarse", comm: MPI.Comm = MPI.COMM_WORLD,
                 skip_far: bool | None = None) -> SurfaceData:
    """The outer skin of the posed hand as a triangle surface only (no volume mesh; a few
    seconds of surface meshing after the OCC geometry), region-coded like the volume mesh's
    skin facets. Built on rank 0, returned on every rank. Used to place objects and to estimate
    contact postures before the volume mesh is made."""
    import gmsh

    if level not in LEVELS:
        raise InputError(f"mesh level '{level}': choose from {', '.join(LEVELS)}")
    digits = parse_digits(digits)
    partial = digits != DIGITS
    skip_far = partial if skip_far is None else (skip_far and partial)
    skel = build_skeleton(subject, pose)
    check_bones(skel)
    surf, error = None, None
    if comm.rank == 0:
        ensure_gmsh(gmsh)
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("hand_surface")
        try:
            occ_hand = build_occ(gmsh, skel, digits, trim_carpus=skip_far)
            lv = dict(LEVELS[level])
            _size_fields(gmsh, skel, digits, lv, palm_contact=not skip_far, far=skip_far)
            gmsh.model.mesh.generate(2)
            node_tags, coords, _ = gmsh.model.mesh.getNodes()
            X = np.zeros((int(node_tags.max()) + 1, 3))
            X[node_tags] = coords.reshape(-1, 3)
            tris, _, codes = _outer_triangles(gmsh.model, occ_hand, X, skel, digits)
            used = np.unique(tris.ravel())
            surf = SurfaceData(X[used], np.searchsorted(used, tris), codes)
        except InputError as exc:
            error = str(exc)
        except Exception as exc:  # gmsh/OCC failures: report, do not hang the other ranks
            error = f"surface meshing failed for pose {pose.source}: {exc}"
        release_gmsh(gmsh)
    idle_wait(comm)
    error = comm.bcast(error, root=0)
    if error:
        raise InputError(error)
    return comm.bcast(surf, root=0)


def whole_hand_cells_estimate(skel: Skeleton, level: str) -> int:
    """Cell count of the whole hand of this subject at ``level``, estimated from the measured
    S01 counts (``WHOLE_HAND_CELLS_S01``, neutral pose) scaled by hand length x breadth x
    thickness relative to S01 (the posture changes the count by ~1 %)."""
    h = skel.subject.hand
    scale = (h.hand_length_mm * h.hand_breadth_mm * h.hand_thickness_mm) / S01_HAND_BOX_MM3
    return int(round(WHOLE_HAND_CELLS_S01[level] * scale))


def skipped_report(skel: Skeleton, digits: tuple[str, ...], level: str, kept: tuple[str, ...],
                   cells: int, skip_far: bool, h_far: float) -> dict:
    """What a partial hand leaves out and what it saves (``quality["skipped"]``)."""
    from handfe.anatomy.tables import CARPALS, ligaments

    dropped_digits = [d for d in DIGITS if d not in digits]
    dropped_bones = [b for b in skel.bones if b not in kept]
    kept_set = set(kept)
    lig_dropped = [lg for lg in ligaments()
                   if lg.bone_a not in kept_set or lg.bone_b not in kept_set]
    # a ligament from a kept bone to a cut-away carpal: carpals are fixed in the hand frame,
    # so the spring still acts (against a fixed point) although the carpal is not meshed
    lig_carpal = [lg.name for lg in lig_dropped
                  if {lg.bone_a, lg.bone_b} & kept_set
                  and ({lg.bone_a, lg.bone_b} - kept_set) <= set(CARPALS)]
    whole = whole_hand_cells_estimate(skel, level)
    regions = []
    if dropped_digits:
        regions.append(f"digits {', '.join(dropped_digits)} and the palm part carrying them "
                       "(cut face tag 91)")
    if skip_far:
        h = LEVELS[level]["h"]
        regions += ["carpus and wrist stub proximal to the kept metacarpal bases (cut face "
                    "tag 91; no wrist face 90)"]
        regions += ([f"coarse mesh (h_far = {h_far} mm instead of h = {h} mm) away from the "
                     "kept digits' middle/distal segments and MCP joints, no palm refinement"]
                    if h_far > h else ["no palm refinement (meshing at h_far failed: retried "
                                       f"at h = {h} mm)"])
    return {
        "digits": dropped_digits,
        "bones": dropped_bones,
        "ligaments": [lg.name for lg in lig_dropped],
        "ligaments_to_dropped_carpals": lig_carpal,
        "regions": regions,
        "cells": cells,
        "cells_whole_hand_estimate": whole if dropped_digits else cells,
        "cells_saved_estimate": max(0, whole - cells) if dropped_digits else 0,
        "fraction_of_whole_hand": round(cells / whole, 3) if dropped_digits else 1.0,
        "estimate": "whole-hand count at the same level: measured S01 count (neutral pose) "
                    "scaled by hand length x breadth x thickness",
    }


def _skin_thickness(gmsh, skel, occ_hand, X, tris, digits, n_max: int = 120) -> dict:
    """Skin thickness at outer-surface mesh nodes away from creases: mid-shaft of the phalanges
    and the middle of the palm; distance from the node (on the CAD surface) to the closest point
    of the skin's inner surface (gmsh getClosestPoint on the CAD)."""
    model = gmsh.model
    ext = {abs(s) for _, s in model.getBoundary([(3, v) for v in occ_hand.skin],
                                                  combined=False, oriented=False)}
    inner = sorted(ext - set(occ_hand.outer_surfaces) - set(occ_hand.wrist_surfaces)
                   - set(occ_hand.cut_surfaces))
    nodes = np.unique(tris.ravel())
    P = X[nodes]
    pick = []
    for d in digits:
        for i in skel.digit_primitives[d]:
            p = skel.primitives[i]
            if p.kind not in ("cone", "ccone"):
                continue
            q = p.frame.inverse_apply(P)
            t = q[:, 1] / p.dims[0]
            ok = (t > 0.35) & (t < 0.65) & (np.abs(p.level(P) - 1.0) < 0.02)
            pick += list(np.flatnonzero(ok)[:: max(1, ok.sum() // 8)][:8])
    H = skel.hand_frame
    qh = H.inverse_apply(P)
    lev = np.min(np.stack([skel.primitives[i].level(P) for d in digits
                           for i in skel.digit_primitives[d]], axis=1), axis=1)
    far_cut = np.ones(len(P), dtype=bool)
    for p0, n in occ_hand.cut_planes:
        far_cut &= np.abs((P - p0) @ n) > 8.0
    palm_ok = np.flatnonzero((lev > 1.6) & (qh[:, 1] > 15.0) & (qh[:, 1] < 45.0)
                             & (np.abs(qh[:, 2]) > 10.0) & far_cut)
    pick += list(palm_ok[:: max(1, len(palm_ok) // 16)][:16])
    pick = pick[:n_max]
    # nearest inner-surface triangle first (robust: the mesh is trimmed), then gmsh's exact
    # closest point on that CAD face (removes the chord error of the coarse triangles); the CAD
    # projection is accepted only if it stays near the triangle's projection
    from scipy.spatial import cKDTree

    tri_list, face_of = [], []
    for s in inner:
        _, _, nt = model.mesh.getElements(2, s)
        t = nt[0].reshape(-1, 3).astype(np.int64)
        tri_list.append(t)
        face_of.append(np.full(len(t), s))
    T = np.concatenate(tri_list)
    face_of = np.concatenate(face_of)
    tree = cKDTree(X[T].mean(axis=1))
    dist = []
    for k in pick:
        x = P[k]
        _, idx = tree.query(x, k=min(40, len(T)))
        d, q = _point_triangles(x, X[T[idx]])
        j = int(np.argmin(d))
        cp, _ = model.getClosestPoint(2, int(face_of[idx[j]]), x.tolist())
        cp = np.asarray(cp)
        dcad = float(np.linalg.norm(cp - x))
        dist.append(dcad if np.linalg.norm(cp - q[j]) < 0.5 else float(d[j]))
    dist = np.array(dist) if dist else np.array([np.nan])
    return {"nominal": skel.subject.hand.skin_thickness_mm, "n_points": int(len(pick)),
            "min": float(np.min(dist)), "max": float(np.max(dist)),
            "mean": float(np.mean(dist)),
            "where": "mid-shaft of each phalanx and the middle of the palm (away from creases, "
                     "the wrist and palm-cut faces)"}


def idle_wait(comm: MPI.Comm, poll_s: float = 0.05) -> None:
    """Barrier that sleeps instead of spinning: while rank 0 runs gmsh, the other ranks would
    otherwise busy-poll in MPI and take a core from it on a 2-core machine."""
    if comm.size == 1:
        return
    req = comm.Ibarrier()
    while not req.Test():
        time.sleep(poll_s)


def _point_triangles(x: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from point x to each triangle (m, 3, 3) and the closest points (m, 3)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    # sample-free exact projection: barycentric clamp (Ericson, Real-Time Collision Detection)
    ab, ac, ap = b - a, c - a, x - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = x - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp_ = x - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp_), np.einsum("ij,ij->i", ac, cp_)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v = vb / denom
        w = vc / denom
    q = a + ab * v[:, None] + ac * w[:, None]
    # fall back to the closest of vertices / edge points where the projection leaves the face
    outside = ~((va >= 0) & (vb >= 0) & (vc >= 0))
    if np.any(outside):
        cand = []
        for p0, p1 in ((a, b), (b, c), (c, a)):
            e = p1 - p0
            t = np.clip(np.einsum("ij,ij->i", x - p0, e) / np.einsum("ij,ij->i", e, e), 0, 1)
            cand.append(p0 + e * t[:, None])
        cand = np.stack(cand, axis=1)
        dd = np.linalg.norm(cand - x, axis=2)
        best = cand[np.arange(len(tri)), np.argmin(dd, axis=1)]
        q = np.where(outside[:, None], best, q)
    return np.linalg.norm(q - x, axis=1), q


def hand_cache_path(subject: Anthropometry, pose: Pose, digits: tuple[str, ...], level: str,
                    skip_far: bool) -> Path | None:
    """Where the hand mesh of these inputs is cached (:mod:`handfe.meshcache`; None if the
    cache is off). The key: subject, joint values and pose name, digits, level, skip_far, the
    gmsh version, the anatomy and kinematics sources and the anatomy tables."""
    from handfe.meshcache import cache_path

    here = Path(__file__).resolve().parent
    sources = [*here.glob("*.py"), here.parent / "kinematics.py", *ANATOMY_DIR.glob("*.csv")]
    subj = asdict(subject)
    subj["source"] = _in_repo(subj.get("source", ""))
    key = {"subject": subj, "pose": sorted(pose.values.items()),
           "pose_source": _in_repo(pose.source), "digits": list(digits), "level": level,
           "skip_far": bool(skip_far)}
    return cache_path("hand", key, sources)


def _in_repo(text: str) -> str:
    """``text`` with this checkout's root removed from the paths in it, so that two clones
    (or worktrees) of the same inputs share their cached meshes (HXT meshes differ run to run,
    so a shared mesh is also the same mesh)."""
    from handfe.paths import REPO_ROOT

    return str(text).replace(f"{REPO_ROOT}/", "")


def _read_cached_hand(gmsh, path: Path | None) -> tuple[dict | None, str | None]:
    """(result, None) for a cached mesh (loaded into gmsh), (None, error) for a cached meshing
    failure, (None, None) on a miss. A cached failure is the gmsh/OCC error of the same
    inputs (the pinch's fully pre-closed posture fails at the same point every run), so a
    grasp's retry ladder moves on at once instead of meshing for ~25 s to fail again."""
    from handfe.meshcache import open_cached

    if path is None:
        return None, None
    failed = path.with_suffix(".failed.json")
    if failed.exists():
        with contextlib.suppress(OSError, ValueError, KeyError):
            return None, (json.loads(failed.read_text())["error"] + f"{CACHED_FAILURE}: {failed};"
                          " HANDFE_MESH_CACHE=0 or deleting the file meshes it again)")
    side = path.with_suffix(".npz")
    if not side.exists():
        return None, None
    try:
        with np.load(side, allow_pickle=False) as z:
            quality = json.loads(str(z["quality"]))
            # JSON object keys are strings: the facet tags were ints
            quality["skin_area_by_tag_mm2"] = {
                int(k): v for k, v in quality.get("skin_area_by_tag_mm2", {}).items()}
            surface = SurfaceData(z["points"], z["triangles"], z["codes"])
    except (OSError, ValueError, KeyError):
        return None, None
    if not open_cached(gmsh, path):
        return None, None
    quality["from_cache"] = True
    return {"quality": quality, "surface": surface}, None


def _cache_hand(gmsh, path: Path | None, result: dict) -> None:
    """Store the mesh and, next to it, its quality report and outer skin triangles (the .npz is
    written first: a reader needs both)."""
    from handfe.meshcache import write_atomically, write_mesh

    if path is None:
        return
    surf = result["surface"]

    def write(tmp: Path) -> None:
        with tmp.open("wb") as fh:
            np.savez(fh, quality=np.array(json.dumps(result["quality"], default=_plain)),
                     points=surf.points, triangles=surf.triangles, codes=surf.codes)

    write_atomically(path.with_suffix(".npz"), write)
    write_mesh(gmsh, path)


def _plain(o):
    """JSON fallback for numpy scalars and arrays."""
    return o.tolist() if hasattr(o, "tolist") else str(o)


def failure_cause(error: str, width: int = 80) -> str:
    """The cause in a meshing error, for a progress line: the text after the pose's
    description ("meshing failed for pose P ...: CAUSE"), "; cached" for a cached failure
    (the full message, in ``summary.json``, names its file), at most ``width`` characters."""
    cause, cached, _ = error.split(": ", 1)[-1].partition(CACHED_FAILURE)
    if len(cause) > width:
        cause = cause[:width - 3] + "..."
    return cause + ("; cached" if cached else "")


def _cache_failure(path: Path | None, error: str) -> None:
    from handfe.meshcache import write_atomically

    if path is not None:  # shared by every checkout: the message names paths in the repo
        write_atomically(path.with_suffix(".failed.json"),
                         lambda tmp: tmp.write_text(json.dumps({"error": _in_repo(error)})))


def build_hand(subject: Anthropometry, pose: Pose | None = None, *,
               digits: str | tuple[str, ...] | None = None, level: str = "reduced",
               comm: MPI.Comm = MPI.COMM_WORLD, skip_far: bool | None = None) -> HandModel:
    """Posed, meshed hand (gmsh on rank 0, mesh distributed over ``comm``).

    ``digits``: the digits to mesh (default all); a partial hand keeps the palm part carrying
    them. ``skip_far`` (partial hands only; default True for a partial hand, False for the
    whole hand): also cut away the carpus and the wrist stub a few mm proximal to the kept
    metacarpal bases (the carpals are dropped; the cut face is tagged 91 like the side cuts,
    and there is no wrist face 90), mesh at ``h_far`` away from the kept digits' middle and
    distal segments and do not refine the palm.
    ``quality["skipped"]`` lists the dropped digits and bones and the cells saved."""
    import dolfinx.fem  # noqa: F401  (import dolfinx fully before dolfinx.io: circular import)
    import gmsh
    from dolfinx import mesh as dmesh
    from dolfinx.io import gmshio

    if level not in LEVELS:
        raise InputError(f"mesh level '{level}': choose from {', '.join(LEVELS)}")
    digits = parse_digits(digits)
    partial = digits != DIGITS
    if skip_far is None:
        skip_far = partial
    elif skip_far and not partial:
        raise InputError("skip_far needs a partial hand (digits=...): the whole hand keeps "
                         "its carpus, wrist and palm refinement")
    pose = pose or Pose.neutral()
    skel = build_skeleton(subject, pose)
    check_bones(skel)
    result, error = None, None
    if comm.rank == 0:
        ensure_gmsh(gmsh)
        gmsh.option.setNumber("General.Terminal", 0)
        try:
            path = hand_cache_path(subject, pose, digits, level, skip_far)
            result, error = _read_cached_hand(gmsh, path)
        except Exception:  # a cache problem must not fail (or, on rank 0 alone, hang) a run
            path, result, error = None, None, None
        if result is None and error is None:
            gmsh.model.add("hand")
            try:
                result = _mesh_rank0(gmsh, skel, digits, level, skip_far)
                _cache_hand(gmsh, path, result)
            except InputError as exc:
                error = str(exc)
            except Exception as exc:  # gmsh/OCC failures: report, do not hang the other ranks
                error = f"meshing failed for pose {pose.source}: {exc}"
                if not isinstance(exc, MemoryError | OSError):  # not a property of the inputs
                    _cache_failure(path, error)
    idle_wait(comm)
    error = comm.bcast(error, root=0)
    if error:
        if comm.rank == 0:
            release_gmsh(gmsh)
        raise InputError(error)
    msh, ct, ft = gmshio.model_to_mesh(gmsh.model, comm, 0, gdim=3)
    if comm.rank == 0:
        release_gmsh(gmsh)
    quality = comm.bcast(result["quality"] if result else None, root=0)
    # cells: nail = skin cells inside the nail boxes
    tdim = msh.topology.dim
    boxes = nail_boxes(skel, digits)
    cvals = ct.values.copy()
    skin_cells = ct.indices[cvals == CELL_TAGS["skin"]]
    if len(skin_cells):
        mid = dmesh.compute_midpoints(msh, tdim, skin_cells)
        cvals[np.isin(ct.indices, skin_cells[in_nail(mid, boxes)])] = CELL_TAGS["nail"]
    cell_tags = dmesh.meshtags(msh, tdim, ct.indices, cvals.astype(np.int32))
    cell_tags.name = "cell_tags"
    # facets: outer skin split by region and phalanx
    fvals = ft.values.copy()
    outer = ft.indices[fvals == SKIN_OUTER_GMSH]
    if len(outer):
        mid = dmesh.compute_midpoints(msh, tdim - 1, outer)
        regions, phal = skel.classify(mid, digits)
        codes = np.array([region_code(r, p) for r, p in zip(regions, phal, strict=True)])
        fvals[fvals == SKIN_OUTER_GMSH] = codes
    facet_tags = dmesh.meshtags(msh, tdim - 1, ft.indices, fvals.astype(np.int32))
    facet_tags.name = "facet_tags"
    tags, groups = tag_names(digits)
    return HandModel(msh, cell_tags, facet_tags, tags, groups, skel, digits, level, quality,
                     result["surface"] if result else None)

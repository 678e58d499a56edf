"""Import path: a subject's segmented surfaces (outer skin + one closed surface per bone) to the
same tagged tetrahedral model as :func:`handfe.anatomy.build_hand`.

Checks (each refusal names the file and the defect): the file loads as a triangle surface; it
is watertight after safe repairs (merging duplicate vertices, dropping degenerate and duplicate
faces, filling single-triangle holes, making the winding consistent); it encloses a positive
volume; bone files are named after the bones of ``anatomy/bones.csv``; every bone lies inside
the skin's inner surface (the skin offset inwards by the skin thickness) and no two bones
overlap. Surface self-intersections that these checks miss are caught by gmsh's boundary
recovery and reported with the file names.

Differences from the generated model: no nails (cell tag 3 is absent), no wrist or palm-cut
tags (the imported skin is one closed surface), skin regions come from the nearest bone
(metacarpals and carpals -> palm), and bone frames are the bones' principal axes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mpi4py import MPI

from handfe.anatomy.meshing import (
    BONE_TAG0,
    CELL_TAGS,
    LEVELS,
    SKIN_OUTER_GMSH,
    HandModel,
    _tet_quality,
    region_code,
    tag_names,
)
from handfe.anatomy.tables import bones as bone_table
from handfe.errors import InputError

SURFACE_SUFFIXES = (".stl", ".obj", ".ply")


def load_surface(path: str | Path, what: str = "surface"):
    """Load a closed triangle surface with trimesh, repair what is safe, refuse the rest."""
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: {what} file not found")
    try:
        m = trimesh.load(p, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"{p}: cannot read the {what} ({exc})") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) < 4:
        raise InputError(f"{p}: no triangle surface in the file")
    m.merge_vertices()
    m.update_faces(m.nondegenerate_faces())
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    if not m.is_watertight:
        _fill_triangle_holes(m)
    if not m.is_watertight:
        edges = trimesh.grouping.group_rows(m.edges_sorted, require_count=1)
        raise InputError(f"{p}: the {what} is not watertight ({len(edges)} open edges after "
                         "merging vertices and filling small holes); close it before import")
    if not m.is_winding_consistent:
        raise InputError(f"{p}: inconsistent triangle orientation (flipped triangles or a "
                         "non-manifold surface)")
    if m.volume < 0:
        m.invert()  # consistently inward: turn outward (a safe repair)
    if m.volume <= 0:
        raise InputError(f"{p}: the {what} encloses no volume")
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    adj = m.face_adjacency
    g = coo_matrix((np.ones(len(adj)), (adj[:, 0], adj[:, 1])), shape=(len(m.faces),) * 2)
    n_bodies = connected_components(g, directed=False)[0]
    if n_bodies != 1:
        raise InputError(f"{p}: the {what} has {n_bodies} separate pieces; expected one")
    return m


def _fill_triangle_holes(m) -> None:
    """Close holes bounded by exactly three open edges (a missing triangle): a safe repair.
    (trimesh's own fill_holes needs networkx, which is not a dependency.)"""
    import trimesh

    open_rows = trimesh.grouping.group_rows(m.edges_sorted, require_count=1)
    if len(open_rows) == 0:
        return
    directed = m.edges[open_rows]  # orientation of the face that owns the open edge
    nxt = {int(a): int(b) for a, b in directed}
    new = []
    seen = set()
    for a in list(nxt):
        if a in seen:
            continue
        b = nxt.get(a)
        c = nxt.get(b) if b is not None else None
        if c is not None and nxt.get(c) == a:
            new.append([a, c, b])  # reversed: the new face must be oriented like its neighbours
            seen.update((a, b, c))
    if new:
        m.faces = np.vstack([m.faces, np.asarray(new)])


def winding_number(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalised winding number of points w.r.t. a closed outward-oriented triangle surface
    (1 inside, 0 outside; Van Oosterom-Strackee solid angles)."""
    out = np.zeros(len(points))
    A, B, C = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    for k in range(0, len(points), 256):
        P = points[k:k + 256, None, :]
        a, b, c = A[None] - P, B[None] - P, C[None] - P
        la, lb, lc = (np.linalg.norm(v, axis=2) for v in (a, b, c))
        det = np.einsum("ijk,ijk->ij", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ijk,ijk->ij", a, b) * lc
               + np.einsum("ijk,ijk->ij", b, c) * la + np.einsum("ijk,ijk->ij", c, a) * lb)
        out[k:k + 256] = np.arctan2(det, den).sum(axis=1) / (2.0 * np.pi)
    return out


def _offset_inwards(m, t: float, path: Path):
    """Inner skin surface: vertices moved inwards along the vertex normals by ``t`` mm."""
    import trimesh

    inner = trimesh.Trimesh(m.vertices - t * m.vertex_normals, m.faces.copy(), process=False)
    if inner.volume <= 0 or inner.volume >= m.volume:
        raise InputError(f"{path}: the inward offset by the skin thickness {t:g} mm is not a "
                         "valid surface (too thin somewhere)")
    # every offset vertex must lie inside the skin, at about t from it
    sample = inner.vertices[:: max(1, len(inner.vertices) // 400)]
    if np.any(winding_number(sample, m.vertices, m.faces) < 0.5):
        raise InputError(f"{path}: the inward offset by {t:g} mm leaves the skin (surface too "
                         "curved or too thin for this skin thickness)")
    # no flipped triangles (a fold of the offset)
    n0, n1 = m.face_normals, inner.face_normals
    if np.any(np.einsum("ij,ij->i", n0, n1) < 0.0):
        raise InputError(f"{path}: the inward offset by {t:g} mm folds over itself (creases "
                         "sharper than the skin thickness); remesh the skin more finely")
    return inner


def import_hand(skin_path: str | Path, bones_dir: str | Path, *, skin_thickness_mm: float = 1.2,
                level: str = "reduced", comm: MPI.Comm = MPI.COMM_WORLD) -> HandModel:
    """Tetrahedral, tagged model from a closed skin surface and a directory of bone surfaces."""
    import dolfinx.fem  # noqa: F401  (import dolfinx fully before dolfinx.io: circular import)
    import gmsh
    from dolfinx import mesh as dmesh
    from dolfinx.io import gmshio

    from handfe.anatomy import meshing

    if level not in LEVELS:
        raise InputError(f"mesh level '{level}': choose from {', '.join(LEVELS)}")
    result, error = None, None
    if comm.rank == 0:
        try:
            result = _import_rank0(gmsh, Path(skin_path), Path(bones_dir), skin_thickness_mm,
                                   level, meshing)
        except InputError as exc:
            error = str(exc)
        except Exception as exc:
            error = f"{skin_path}: import meshing failed: {exc}"
    meshing.idle_wait(comm)
    error = comm.bcast(error, root=0)
    if error:
        if comm.rank == 0:
            meshing.release_gmsh(gmsh)
        raise InputError(error)
    msh, ct, ft = gmshio.model_to_mesh(gmsh.model, comm, 0, gdim=3)
    if comm.rank == 0:
        meshing.release_gmsh(gmsh)
    info = comm.bcast({k: v for k, v in result.items() if k != "kd"} if result else None, 0)
    bone_pts, bone_lab = comm.bcast((result["bone_pts"], result["bone_lab"]) if result
                                    else None, 0)
    from scipy.spatial import cKDTree

    tree = cKDTree(bone_pts)
    names = list(bone_table())
    tdim = msh.topology.dim
    fvals = ft.values.copy()
    outer = ft.indices[fvals == SKIN_OUTER_GMSH]
    if len(outer):
        mid = dmesh.compute_midpoints(msh, tdim - 1, outer)
        _, idx = tree.query(mid)
        fvals[fvals == SKIN_OUTER_GMSH] = [_bone_region_code(names[bone_lab[i]]) for i in idx]
    facet_tags = dmesh.meshtags(msh, tdim - 1, ft.indices, fvals.astype(np.int32))
    facet_tags.name = "facet_tags"
    ct.name = "cell_tags"
    digits = tuple(d for d in ("thumb", "index", "middle", "ring", "little")
                   if any(n.startswith(d) for n in info["quality"]["bones"]))
    tags, groups = tag_names(digits)
    return HandModel(msh, ct, facet_tags, tags, groups, None, digits, level, info["quality"],
                     result["surface"] if result else None)


def _bone_region_code(bone: str) -> int:
    b = bone_table()[bone]
    if b.kind != "phalanx":
        return region_code("palm", "")
    return region_code(b.digit, b.segment)


def _import_rank0(gmsh, skin_path: Path, bones_dir: Path, t: float, level: str, meshing):
    import time

    t0 = time.perf_counter()
    skin = load_surface(skin_path, "skin surface")
    if not bones_dir.is_dir():
        raise InputError(f"{bones_dir}: bones directory not found")
    table = bone_table()
    names = list(table)
    files = sorted(f for f in bones_dir.iterdir() if f.suffix.lower() in SURFACE_SUFFIXES)
    if not files:
        raise InputError(f"{bones_dir}: no bone surfaces (*.stl, *.obj, *.ply)")
    bones = {}
    for f in files:
        if f.stem not in table:
            raise InputError(f"{f}: unknown bone name '{f.stem}' (names: anatomy/bones.csv)")
        bones[f.stem] = load_surface(f, "bone surface")
    inner = _offset_inwards(skin, t, skin_path)
    for n, b in bones.items():
        pts = b.vertices[:: max(1, len(b.vertices) // 150)]
        if np.any(winding_number(pts, inner.vertices, inner.faces) < 0.5):
            raise InputError(f"{bones_dir / n}: bone {n} is not inside the skin's inner surface "
                             f"(skin {skin_path.name} offset by {t:g} mm)")
    order = list(bones)
    for i, a in enumerate(order):
        for b in order[i + 1:]:
            A, B = bones[a], bones[b]
            if np.any(A.bounds[1] < B.bounds[0]) or np.any(B.bounds[1] < A.bounds[0]):
                continue
            pts = A.vertices[:: max(1, len(A.vertices) // 150)]
            if np.any(winding_number(pts, B.vertices, B.faces) > 0.5):
                raise InputError(f"{bones_dir}: bones {a} and {b} intersect")
    # --- gmsh model from discrete surfaces
    meshing.ensure_gmsh(gmsh)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("imported")
    node0 = [1]

    def add_surface(m) -> int:
        s = gmsh.model.addDiscreteEntity(2)
        n = len(m.vertices)
        tags = np.arange(node0[0], node0[0] + n)
        gmsh.model.mesh.addNodes(2, s, tags.tolist(), m.vertices.ravel().tolist())
        gmsh.model.mesh.addElementsByType(s, 2, [], (tags[m.faces]).ravel().tolist())
        node0[0] += n
        return s

    s_out = add_surface(skin)
    s_in = add_surface(inner)
    s_bones = {n: add_surface(bones[n]) for n in order}
    geo = gmsh.model.geo
    l_out = geo.addSurfaceLoop([s_out])
    l_in = geo.addSurfaceLoop([s_in])
    l_b = [geo.addSurfaceLoop([s]) for s in s_bones.values()]
    v_skin = geo.addVolume([l_out, l_in])
    v_sub = geo.addVolume([l_in] + l_b)
    geo.synchronize()
    gmsh.model.addPhysicalGroup(3, [v_skin], CELL_TAGS["skin"])
    gmsh.model.addPhysicalGroup(3, [v_sub], CELL_TAGS["subcutaneous"])
    gmsh.model.addPhysicalGroup(2, [s_out], SKIN_OUTER_GMSH)
    for n, s in s_bones.items():
        gmsh.model.addPhysicalGroup(2, [s], BONE_TAG0 + names.index(n))
    gmsh.option.setNumber("Mesh.MeshSizeMax", LEVELS[level]["h"])
    gmsh.option.setNumber("Mesh.Algorithm3D", meshing.ALGORITHM_3D)
    t1 = time.perf_counter()
    try:
        gmsh.model.mesh.generate(3)
    except Exception as exc:
        raise InputError(f"{skin_path} / {bones_dir}: tetrahedral meshing failed ({exc}); the "
                         "surfaces probably intersect each other or themselves") from None
    t2 = time.perf_counter()
    nt, coords, _ = gmsh.model.mesh.getNodes()
    X = np.zeros((int(nt.max()) + 1, 3))
    X[nt] = coords.reshape(-1, 3)
    vols, tets_all = {}, []
    for name, v in (("skin", v_skin), ("subcutaneous", v_sub)):
        _, _, ntags = gmsh.model.mesh.getElements(3, v)
        tets = ntags[0].reshape(-1, 4).astype(np.int64)
        if len(tets) == 0:
            raise InputError(f"{skin_path}: no tetrahedra in the {name} volume")
        tets_all.append(tets)
        P = X[tets]
        vols[name] = float(np.abs(np.einsum("ij,ij->i", P[:, 1] - P[:, 0], np.cross(
            P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]))).sum() / 6.0)
    tets = np.concatenate(tets_all)
    q, min_dih = _tet_quality(X, tets)
    bone_vol = float(sum(b.volume for b in bones.values()))
    bone_pts = np.concatenate([b.vertices for b in bones.values()])
    bone_lab = np.concatenate([np.full(len(bones[n].vertices), names.index(n)) for n in order])
    codes = np.array([_bone_region_code(names[bone_lab[i]]) for i in
                      _nearest(bone_pts, skin.triangles_center)])
    area = skin.area_faces
    area_region = {r: 0.0 for r in meshing.REGIONS}
    for c, a in zip(codes, area, strict=True):
        area_region[meshing.REGIONS[(c // 10) % 10 - 1]] += float(a)
    quality = {
        "level": level, "imported": {"skin": str(skin_path), "bones": str(bones_dir)},
        "cells": int(len(tets)), "vertices": int(len(nt)),
        "quality_measure": "radius ratio 3*r_in/r_circ (1 = regular tetrahedron)",
        "min_quality": float(q.min()), "mean_quality": float(q.mean()),
        "cells_quality_below_0.1": int((q < 0.1).sum()),
        "min_dihedral_angle_deg": min_dih,
        "volume_mm3": vols, "bone_volume_mm3": bone_vol,
        "hand_volume_cm3": float((sum(vols.values()) + bone_vol) / 1000.0),
        "skin_area_mm2": area_region,
        "skin_thickness_mm": {"nominal": t, "method": "vertex-normal offset of the skin"},
        "bones": order, "meshing_time_s": round(t2 - t0, 2),
        "timings_s": {"checks_and_offset": round(t1 - t0, 2), "mesh_generate": round(t2 - t1, 2)},
    }
    surf = meshing.SurfaceData(np.asarray(skin.vertices), np.asarray(skin.faces), codes)
    return {"quality": quality, "surface": surf, "bone_pts": bone_pts, "bone_lab": bone_lab}


def _nearest(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(points).query(queries)[1]


def export_surfaces(model: HandModel, out_dir: str | Path) -> tuple[Path, Path]:
    """Write the model's closed outer surface (``skin.stl``) and one STL per bone cavity
    (``bones/<bone>.stl``), in mm. Serial meshes only (one rank holds all facets)."""
    import trimesh
    from dolfinx import mesh as dmesh
    from dolfinx.cpp import mesh as cpp_mesh

    msh = model.mesh
    if msh.comm.size != 1:
        raise InputError("export_surfaces needs a mesh on one rank (comm=MPI.COMM_SELF)")
    tdim = msh.topology.dim
    msh.topology.create_connectivity(tdim - 1, tdim)
    ext = dmesh.exterior_facet_indices(msh.topology)
    X = msh.geometry.x
    bone_tags = {model.tags[f"bone_{b}"]: b for b in model.bones}
    val = dict(zip(model.facet_tags.indices.tolist(), model.facet_tags.values.tolist(),
                   strict=True))
    out = Path(out_dir)
    (out / "bones").mkdir(parents=True, exist_ok=True)
    skin_f = [f for f in ext if val.get(int(f)) not in bone_tags]
    groups = {"skin": skin_f}
    for tag, name in bone_tags.items():
        groups[name] = [f for f in ext if val.get(int(f)) == tag]
    for name, facets in groups.items():
        # orient=True: normals point out of the tissue (outward for the skin, into the bone)
        tri = cpp_mesh.entities_to_geometry(msh._mesh,  # dolfinx 0.5 wrapper -> C++ mesh
                                            tdim - 1, np.asarray(facets, dtype=np.int32),
                                            True)
        if name != "skin":
            tri = tri[:, ::-1]
        m = trimesh.Trimesh(X[:, :3], tri, process=True)
        m.remove_unreferenced_vertices()
        m.export(out / ("skin.stl" if name == "skin" else f"bones/{name}.stl"))
    return out / "skin.stl", out / "bones"

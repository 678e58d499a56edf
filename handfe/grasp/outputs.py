"""Per-region contact metrics from nodal fields, and the palmar pressure map.

Metrics over the outer skin facets of each region code (see docs/anatomy.md): a facet is the
flat triangle through its deformed vertices; its contact area is the part where the gap
interpolated from the vertices is <= gap_tol (as :func:`handfe.contact.contact_metrics`), the
pressure and tangential traction are the vertex values (P1) integrated with the vertex rule over
the deformed facet. All sums are over owned facets and reduced over ranks.

Forces: with the consistent nodal contact forces (the contact residual at the skin nodes,
``node_force``), each node's force is shared equally by the outer-skin facets around it, so the
regions add up exactly to the force on the object that the equilibrium check uses; the normal
part is along the object's normal at the node. A node's pressure is its normal force over its
tributary area (a third of each facet around it); the peak is the largest, the mean is the
normal load over the tributary area of the loaded nodes (never above the peak; on a coarse mesh
that area is larger than the gap-based contact area). The map uses the nodal pressures. The
vertex-rule integral of the interpolated pressure is the fallback: on a coarse pad (a contact
patch of a few facets) it can differ from the nodal forces several times.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from mpi4py import MPI

from handfe.anatomy.meshing import PHALANGES, REGIONS, SKIN_OUTER_GMSH

METRICS = ("contact_area_mm2", "loaded_area_mm2", "mean_pressure_kPa", "peak_pressure_kPa",
           "normal_force_N", "tangential_force_N")


def region_table(regions: Mapping[str, Mapping[str, float]],
                 skipped: Sequence[str] = ()) -> str:
    """The six regions' rows of regions.csv as a fixed-width text table (the segments stay
    in the file): areas mm2, pressures kPa, forces N; a ``skipped`` digit (not meshed) is
    named as such instead of a row of zeros."""
    head = ("region", "contact mm2", "loaded mm2", "mean kPa", "peak kPa", "normal N",
            "tangential N")
    fmt = ("{:.0f}", "{:.0f}", "{:.0f}", "{:.0f}", "{:.2f}", "{:.2f}")
    shown = [r for r in REGIONS if r in regions and r not in skipped]
    rows = [head] + [(r, *(f.format(regions[r][m]) for f, m in zip(fmt, METRICS, strict=True)))
                     for r in shown]
    widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
    lines = ["  ".join([row[0].ljust(widths[0])] + [c.rjust(w) for c, w in
                                                    zip(row[1:], widths[1:], strict=True)])
             for row in rows]
    gone = [r for r in REGIONS if r in skipped]
    return "\n".join(lines + ([f"not meshed: {', '.join(gone)}"] if gone else []))


#: default threshold (kPa) of the loaded area: the skin where the nodal contact pressure is at
#: least this much (a pressure sensor's view). The contact area (gap <= gap_tol) also counts
#: skin that touches with almost no pressure, and that fringe grows as the mesh follows the
#: object more closely: on the spherical grasp the contact area of the thumb is 165 mm2 at
#: `reduced` and 294 at `default`, its loaded area (10 kPa) 133 and 129 (docs/grasp.md)
LOADED_AREA_KPA = 10.0


def facet_areas(xf: np.ndarray) -> np.ndarray:
    """Areas (mm2) of flat triangles with vertices ``xf`` (n, 3, 3)."""
    return 0.5 * np.linalg.norm(np.cross(xf[:, 1] - xf[:, 0], xf[:, 2] - xf[:, 0]), axis=1)


def loaded_area(facet_area: np.ndarray, p_kPa: np.ndarray, threshold_kPa: float) -> np.ndarray:
    """Each facet's loaded area (mm2): a third of its area (``facet_area``, (n,)) for each of
    its vertices whose pressure (``p_kPa``, (n, 3)) is >= ``threshold_kPa``."""
    return (p_kPa >= threshold_kPa).sum(axis=1) * facet_area / 3.0


def region_of(code: int) -> tuple[str, str]:
    r = (int(code) - SKIN_OUTER_GMSH) // 10
    ph = (int(code) - SKIN_OUTER_GMSH) % 10
    return REGIONS[r - 1], (PHALANGES[ph - 1] if ph else "")


def _shared_count(mesh, fun, nodes: np.ndarray, weights: np.ndarray | None = None
                  ) -> np.ndarray:
    """Per geometry node: the number of ``nodes`` facets (over all ranks) that touch it, or with
    ``weights`` (one per facet vertex, shape of ``nodes``) their sum."""
    from dolfinx import fem
    from dolfinx.cpp.la import ScatterMode

    V = fem.FunctionSpace(mesh, ("CG", 1))
    c = fem.Function(V)
    geo = mesh.geometry.dofmap.array.reshape(-1, len(mesh.geometry.dofmap.links(0)))
    dofs = V.dofmap.list.array.reshape(geo.shape[0], -1)
    g2d = np.full(mesh.geometry.x.shape[0], -1, dtype=np.int64)
    g2d[geo[:, :dofs.shape[1]].reshape(-1)] = dofs.reshape(-1)
    cnt = np.zeros(mesh.geometry.x.shape[0])
    np.add.at(cnt, nodes.reshape(-1), 1.0 if weights is None else weights.reshape(-1))
    used = g2d >= 0
    c.x.array[g2d[used]] = cnt[used]
    c.x.scatter_reverse(ScatterMode.add)
    c.x.scatter_forward()
    out = np.zeros(mesh.geometry.x.shape[0])
    out[used] = c.x.array[g2d[used]]
    return out


def facet_data(model, u1, p1, t1, obstacle, translation, gap_tol_mm: float, node_force=None):
    """Owned outer-skin facets: codes, deformed vertices (nf, 3, 3), gap at vertices, vertex
    pressure (MPa), vertex tangential traction (nf, 3, 3), clipped contact area, full area;
    with ``node_force`` (P1 vector Function, N: the force the skin exerts on the object at each
    node) also each facet vertex's share of it ``f`` (nf, 3, 3)."""
    from dolfinx import cpp

    from handfe.contact import _clip_patch, _node_values

    mesh = model.mesh
    fdim = mesh.topology.dim - 1
    n_owned = mesh.topology.index_map(fdim).size_local
    ft = model.facet_tags
    codes_all = [c for c in model.groups["skin_outer"]]
    sel = np.isin(ft.values, codes_all) & (ft.indices < n_owned)
    facets, codes = ft.indices[sel], ft.values[sel]
    nodes = cpp.mesh.entities_to_geometry(mesh._mesh, fdim, facets, False)[:, :3] \
        if len(facets) else np.zeros((0, 3), dtype=np.int32)
    xdef = mesh.geometry.x[:, :3] + _node_values(u1, mesh)
    xf = xdef[nodes]
    g, n = obstacle.gap_normal(xf.reshape(-1, 3), np.asarray(translation))
    g = g.reshape(-1, 3)
    pv = _node_values(p1, mesh)[:, 0][nodes]
    tv = _node_values(t1, mesh)[nodes] if t1 is not None else np.zeros_like(xf)
    ax = np.eye(3)[:2]
    area_c, _, _, _ = _clip_patch(xf, g - gap_tol_mm, ax) if len(facets) else (
        np.zeros(0), None, None, None)
    full = facet_areas(xf) if len(facets) else np.zeros(0)
    fd = {"codes": codes, "xf": xf, "g": g, "n": n.reshape(-1, 3, 3), "p": pv, "t": tv,
          "area_c": area_c, "area": full}
    if node_force is not None:
        cnt = np.maximum(_shared_count(mesh, node_force, nodes)[nodes], 1.0)
        # tributary (lumped) area of each node: a third of every facet around it
        atrib = _shared_count(mesh, node_force, nodes, np.repeat(full[:, None] / 3.0, 3, 1))
        f = _node_values(node_force, mesh)[nodes]
        fd["f"] = f / cnt[..., None]
        # nodal pressure: the node's normal force over its tributary area (MPa)
        fd["p_node"] = np.maximum(-np.einsum("fvi,fvi->fv", f, fd["n"]), 0.0) \
            / np.maximum(atrib[nodes], 1e-300)
        fd["a_share"] = atrib[nodes] / cnt  # this facet's share of the node's area
    return fd


#: a node counts as loaded (mean pressure, contact area) when its pressure is >= this
#: fraction of the peak nodal pressure over the whole skin, or >= the loaded area's threshold
LOADED_FRACTION = 0.01


def region_metrics(fd: dict, comm: MPI.Comm, loaded_area_kPa: float = LOADED_AREA_KPA
                   ) -> dict[str, dict[str, float]]:
    """Metrics per region (thumb..little, palm) and per digit segment (``index_distal``...);
    ``loaded_area_mm2`` is the skin with nodal pressure >= ``loaded_area_kPa``
    (:func:`loaded_area`), a part of ``contact_area_mm2`` (with nodal forces, exactly)."""
    codes = fd["codes"]
    keys: dict[str, np.ndarray] = {}
    names = [region_of(c) for c in codes]
    for r in REGIONS:
        keys[r] = np.array([n[0] == r for n in names], dtype=bool)
        if r != "palm":
            for ph in PHALANGES:
                if r == "thumb" and ph == "middle":
                    continue
                keys[f"{r}_{ph}"] = np.array([n == (r, ph) for n in names], dtype=bool)
    pm = fd["p"].mean(axis=1) if len(codes) else np.zeros(0)
    # contact area: the part of a facet within gap_tol of the object, or (where the Uzawa
    # multiplier keeps a positive pressure at a small positive gap) its share of vertices with
    # positive pressure, whichever is larger
    frac_p = (fd["p"] > 0).mean(axis=1) if len(codes) else np.zeros(0)
    area_c = np.maximum(fd["area_c"], frac_p * fd["area"]) if len(codes) else np.zeros(0)
    nm = fd["n"].mean(axis=1) if len(codes) else np.zeros((0, 3))
    tm = fd["t"].mean(axis=1) if len(codes) else np.zeros((0, 3))
    nodal = "f" in fd
    if nodal and len(codes):
        f = fd["f"]  # force on the object, shared per facet vertex
        fn_s = -np.einsum("fvi,fvi->fv", f, fd["n"])  # pressing force along -n (>= 0)
        fvec_f = f.sum(axis=1)
        fnorm_f = (-fn_s[..., None] * fd["n"]).sum(axis=1)
    if nodal:
        # "loaded" nodes: at least LOADED_FRACTION of the peak nodal pressure of the whole
        # skin (one threshold for all regions, so segments add up to their digit). The
        # consistent nodal forces leave a dust of tiny forces around a patch, which made a
        # 4.7 N thumb pad 'loaded' over ~200 mm2 on the coarse pinch
        gpeak = comm.allreduce(float(fd["p_node"].max(initial=0.0)) if len(codes) else 0.0,
                               op=MPI.MAX)
        over_kPa = 1e3 * fd["p_node"] >= loaded_area_kPa  # the loaded area's nodes
        # ... and every node of the loaded area (>= loaded_area_kPa): with a 1.3 MPa peak the
        # fraction's 13 kPa made the muscle-driven thumb's contact area 157 mm2 and its
        # loaded area (10 kPa) 194 mm2; the contact area holds the loaded area by definition
        loaded = ((fd["p_node"] >= max(LOADED_FRACTION * gpeak, 1e-300)) | over_kPa) \
            if len(codes) else np.zeros((0, 3), dtype=bool)
        # a flat facet on a curved object touches with its interior (Gauss points) while its
        # vertices stay > gap_tol away (sagitta a^2 / 8R ~ 0.06 mm on the coarse pinch): the
        # gap-based area was 0 under a 4.4 N thumb. A facet's area is at least its share of
        # its loaded nodes' tributary area
        # (this replaces the positive-vertex-pressure share above, which counts the dust)
        if len(codes):
            area_c = np.maximum(fd["area_c"], (fd["a_share"] * loaded).sum(axis=1))
    if nodal and len(codes):
        # the loaded nodes' tributary shares, as the contact area counts them (a region's
        # border node splits its area equally among its facets), so loaded <= contact exactly
        area_l = (fd["a_share"] * over_kPa).sum(axis=1)
    else:
        area_l = loaded_area(fd["area"], 1e3 * (fd["p_node"] if nodal else fd["p"]),
                             loaded_area_kPa)
    out = {}
    for k, m in keys.items():
        area = comm.allreduce(float(area_c[m].sum()), op=MPI.SUM)
        area_loaded = comm.allreduce(float(area_l[m].sum()), op=MPI.SUM)
        if nodal:
            z3 = np.zeros(3)
            # mean pressure = normal load / tributary area of the loaded nodes (an area
            # weighted mean of the nodal pressures, so never above the peak)
            peak = comm.allreduce(float(fd["p_node"][m].max(initial=0.0)), op=MPI.MAX)
            aload = comm.allreduce(float((fd["a_share"][m] * loaded[m]).sum())
                                   if len(codes) else 0.0, op=MPI.SUM)
            psum = comm.allreduce(float((fn_s[m] * loaded[m]).sum()) if len(codes) else 0.0,
                                  op=MPI.SUM)
            fvec = comm.allreduce(fvec_f[m].sum(axis=0) if len(codes) else z3, op=MPI.SUM)
            fnv = comm.allreduce(fnorm_f[m].sum(axis=0) if len(codes) else z3, op=MPI.SUM)
            tvec = fvec - fnv
            nforce = float(np.linalg.norm(fnv))
        else:
            psum = comm.allreduce(float((pm[m] * fd["area"][m]).sum()), op=MPI.SUM)
            aload = area
            peak = comm.allreduce(float(fd["p"][m].max(initial=0.0)), op=MPI.MAX)
            fvec = comm.allreduce((pm[m, None] * nm[m] * fd["area"][m, None]).sum(axis=0),
                                  op=MPI.SUM)
            tvec = comm.allreduce((tm[m] * fd["area"][m, None]).sum(axis=0), op=MPI.SUM)
            nforce = float(np.linalg.norm(fvec))
        out[k] = {"contact_area_mm2": area,
                  "loaded_area_mm2": area_loaded,
                  "mean_pressure_kPa": 1e3 * psum / aload if aload > 0 else 0.0,
                  "peak_pressure_kPa": 1e3 * peak,
                  "normal_force_N": nforce,
                  "tangential_force_N": float(np.linalg.norm(tvec)),
                  "force_vector_N": [float(x) for x in fvec]}
    return out


def pressure_map_png(fd: dict, hand_R: np.ndarray, path: Path, comm: MPI.Comm, *,
                     title: str = "", obstacle_outline=None,
                     facets_npz: Path | None = None) -> None:
    """Palmar view (looking at the palm along hand -z) of the deformed skin, coloured by contact
    pressure (kPa), grey where there is none; region borders drawn in black (collective; rank 0
    draws). ``facets_npz``: also keep the gathered facets there, so ``handfe plot`` can draw the
    map again (another colour scale, another file) without re-running."""
    data = gather_pressure_facets(fd, comm)
    if data is None:
        return
    if facets_npz is not None:
        np.savez_compressed(facets_npz, hand_R=np.asarray(hand_R, dtype=float),
                            title=np.array(title), **data)
    draw_pressure_map(data, hand_R, path, title=title)


def gather_pressure_facets(fd: dict, comm: MPI.Comm) -> dict[str, np.ndarray] | None:
    """The deformed skin facets of every rank on rank 0 (None on the others): ``xf`` (n, 3, 3)
    vertex positions (mm, world frame), ``p_kPa`` (n, 3) vertex contact pressures, ``codes``
    (n,) region codes."""
    allp = comm.gather((fd["xf"], fd.get("p_node", fd["p"]), fd["codes"]), root=0)
    if comm.rank != 0:
        return None
    return {"xf": np.concatenate([a[0] for a in allp]),
            "p_kPa": np.concatenate([a[1] for a in allp]) * 1e3,
            "codes": np.concatenate([a[2] for a in allp])}


def load_pressure_facets(path: Path) -> tuple[dict[str, np.ndarray], np.ndarray, str]:
    """(facets, hand rotation, title) that :func:`pressure_map_png` kept in ``path``."""
    with np.load(path) as z:
        data = {k: z[k] for k in ("xf", "p_kPa", "codes")}
        return data, z["hand_R"], str(z["title"])


def region_labels(xy: np.ndarray, pf: np.ndarray, loaded: np.ndarray, reg: np.ndarray
                  ) -> list[tuple[str, float, float]]:
    """(region, x, y) of each region (REGIONS order) with loaded facets: the pressure-weighted
    centroid of those facets in the map's plane (mm); ``xy`` (n, 3, 2) facet vertices, ``pf``
    facet pressures, ``loaded`` facet mask, ``reg`` facet region names."""
    out = []
    for r in REGIONS:
        m = loaded & (reg == r)
        if m.any():
            w = pf[m]
            c = (xy[m].mean(axis=1) * w[:, None]).sum(axis=0) / w.sum()
            out.append((r, float(c[0]), float(c[1])))
    return out


def draw_pressure_map(data: dict[str, np.ndarray], hand_R: np.ndarray, path: Path, *,
                      title: str = "", vmax_kPa: float | None = None) -> float:
    """Draw the palmar pressure map of gathered facets (:func:`gather_pressure_facets`) into
    ``path``; colour scale 0..``vmax_kPa`` (default the largest facet pressure, kPa), returned;
    each loaded region named at its patch.
    The loaded facets are drawn over the unloaded ones whatever their depth: in a power grasp
    the pads face the object inside the closed hand and the skin around them would hide
    them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PolyCollection

    xf, p, codes = data["xf"], data["p_kPa"], data["codes"]
    xh = xf @ hand_R  # world -> hand frame coordinates (rows)
    depth = xh[:, :, 2].mean(axis=1)
    pf = p.mean(axis=1)
    p_max = max(float(pf.max(initial=0.0)), 1e-9)
    vmax = float(vmax_kPa) if vmax_kPa else p_max
    loaded = pf > 1e-3 * p_max
    order = np.lexsort((depth, loaded))  # unloaded, then loaded; palmar (+z) last = on top
    xy = xh[order][:, :, :2]  # seen from the palmar side: radial (+x) on the right
    pf, loaded = pf[order], loaded[order]
    cmap = plt.get_cmap("inferno_r")
    colors = np.where(loaded[:, None], cmap(np.clip(pf / vmax, 0, 1)),
                      np.array([0.85, 0.85, 0.85, 1.0]))
    fig, ax = plt.subplots(figsize=(6.5, 8), dpi=110)
    ax.add_collection(PolyCollection(xy, facecolors=colors, edgecolors="none"))
    # region borders: edges between facets of different regions (visible ones only)
    reg = np.array([region_of(c)[0] for c in codes[order]])
    edges: dict[tuple, tuple[str, int]] = {}
    segs = []
    keyx = np.round(xh[order][:, :, :3], 3)
    for i in range(len(order)):
        for a, b in ((0, 1), (1, 2), (2, 0)):
            k = tuple(sorted((tuple(keyx[i, a]), tuple(keyx[i, b]))))
            if k in edges and edges[k][0] != reg[i]:
                segs.append([xy[i, a], xy[i, b]])
            edges[k] = (reg[i], i)
    if segs:
        ax.add_collection(LineCollection(segs, colors="k", linewidths=0.5))
    for name, x, y in region_labels(xy, pf, loaded, reg):
        ax.annotate(name, (x, y), xytext=(10, 10), textcoords="offset points", fontsize=8,
                    bbox={"boxstyle": "round,pad=0.2", "fc": "white", "alpha": 0.8, "lw": 0},
                    arrowprops={"arrowstyle": "-", "lw": 0.6})
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, vmax))
    fig.colorbar(sm, ax=ax, label="contact pressure (kPa)", shrink=0.7)
    ax.set_aspect("equal")
    ax.autoscale()
    ax.set_xlabel("ulnar  <-  x (mm)  ->  radial   (palmar view)")
    ax.set_ylabel("y (mm), distal up")
    ax.set_title(title or "contact pressure, palmar view")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return vmax


def smallest_tissue_cells(problem, model, obstacle, translation, k: int = 5
                          ) -> list[dict[str, object]]:
    """Where the tissue lost the most volume: the ``k`` tissue cells of smallest J = det F
    (all ranks), each with its centre (mm, reference configuration), the region of the
    nearest outer skin facet and that facet's distance (mm, reference) and the signed distance
    of the deformed centre to the object (mm, < 0 inside). The same list on every rank and
    for any partition."""
    from dolfinx.mesh import compute_midpoints

    comm, msh = problem.comm, model.mesh

    def first(J: np.ndarray, centre: np.ndarray) -> np.ndarray:
        # ties (equal J in congruent cells) broken by the centre: the same on any partition
        c = np.round(centre, 6)
        return np.lexsort((c[:, 2], c[:, 1], c[:, 0], np.round(J, 12)))[:k]

    tissue, J = problem.tissue_cell_J()
    tissue = tissue.astype(np.int32)
    centre = compute_midpoints(msh, 3, tissue) if len(tissue) else np.zeros((0, 3))
    order = first(J, centre)
    cells, centre = tissue[order], centre[order]
    u = problem.displacement()
    udof = u.function_space.dofmap.list.array.reshape(-1, 4)  # P1 tets: 4 vertex blocks
    ux = u.x.array.reshape(-1, 3)
    moved = centre + ux[udof[cells]].mean(axis=1) if len(cells) else centre
    cand = comm.allgather((J[order], centre, moved))
    Jall = np.concatenate([c[0] for c in cand])
    keep = first(Jall, np.concatenate([c[1] for c in cand]))
    Jall = Jall[keep]
    centre = np.concatenate([c[1] for c in cand])[keep]
    moved = np.concatenate([c[2] for c in cand])[keep]
    skin = nearest_skin(model, centre)
    gap = obstacle.gap_normal(moved, np.asarray(translation, dtype=float))[0] \
        if len(keep) else np.zeros(0)
    out: list[dict[str, object]] = []
    for j in range(len(keep)):
        region, dist = skin[j]
        out.append({"J": float(Jall[j]), "centre_mm": [round(float(v), 3) for v in centre[j]],
                    "nearest_skin": region, "skin_distance_mm": round(dist, 3),
                    "object_distance_mm": round(float(gap[j]), 3)})
    return out


def nearest_skin(model, points: np.ndarray) -> list[tuple[str, float]]:
    """For each point (n, 3; mm, reference configuration): the region of the nearest outer
    skin facet ("thumb/proximal", "palm"; "" if there is none) and its distance (mm, to the
    facet's midpoint). Collective: every rank passes the same points and gets the same list."""
    from dolfinx.mesh import compute_midpoints
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=float).reshape(-1, 3)
    ft = model.facet_tags
    on = np.isin(ft.values, np.asarray(model.groups["skin_outer"]))
    fac, fval = ft.indices[on], ft.values[on]
    near = np.full(len(points), np.inf)
    code = np.zeros(len(points), dtype=np.int64)
    if len(fac) and len(points):
        near, i = cKDTree(compute_midpoints(model.mesh, 2, fac)).query(points)
        code = fval[i].astype(np.int64)
    best = model.mesh.comm.allgather((near, code))
    out = []
    for j in range(len(points)):
        dist, c = min((float(b[0][j]), int(b[1][j])) for b in best)
        out.append(("/".join(region_of(c)).rstrip("/") if np.isfinite(dist) else "", dist))
    return out


def describe_cell(model, centre: np.ndarray) -> str:
    """Where a tissue cell is, in words: "2.7 mm under the thumb/proximal skin" (its centre's
    distance to the nearest outer skin facet). Collective, as :func:`nearest_skin`."""
    region, dist = nearest_skin(model, centre)[0]
    return f"{dist:.1f} mm under the {region} skin" if region else "no outer skin"

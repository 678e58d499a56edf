"""Outputs: CSV/JSON tables and off-screen pictures (matplotlib Agg). Call the writers on rank 0;
:func:`pad_pressure_png` is collective (it gathers the surface to rank 0)."""

from __future__ import annotations

import csv
import json
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (temp file + rename): no half-written files."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def write_json(path: Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=float) + "\n")


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    """Rows of dicts with the same keys -> CSV (header from the first row)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not rows:
        atomic_write_text(path, "")
        return
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow(r)
    atomic_write_text(path, buf.getvalue())


def _vertex_to_dof(V) -> np.ndarray:
    """For a P1 space on a linear mesh: local vertex index -> local dof index."""
    msh = V.mesh
    tdim = msh.topology.dim
    msh.topology.create_connectivity(tdim, 0)
    c2v = msh.topology.connectivity(tdim, 0)
    n_cells = msh.topology.index_map(tdim).size_local + msh.topology.index_map(tdim).num_ghosts
    nv = msh.topology.index_map(0).size_local + msh.topology.index_map(0).num_ghosts
    out = np.full(nv, -1, dtype=np.int64)
    for c in range(n_cells):
        out[c2v.links(c)] = V.dofmap.cell_dofs(c)
    return out


def surface_triangles(msh, facets: np.ndarray, fields: Sequence[Any]) -> tuple[np.ndarray, ...]:
    """Owned ``facets`` as triangles: reference vertex coordinates (n, 3, 3) and, for each P1
    Function in ``fields``, its vertex values (n, 3, bs) — gathered on rank 0 (None elsewhere)."""
    fdim = msh.topology.dim - 1
    msh.topology.create_connectivity(fdim, 0)
    f2v = msh.topology.connectivity(fdim, 0)
    n_owned = msh.topology.index_map(fdim).size_local
    f = np.asarray(facets, dtype=np.int32)
    f = f[f < n_owned]
    from dolfinx.cpp.mesh import entities_to_geometry

    geo = entities_to_geometry(msh._mesh, fdim, f, False) if len(f) else np.zeros((0, 3), np.int32)
    X = msh.geometry.x[geo] if len(f) else np.zeros((0, 3, 3))
    verts = np.array([f2v.links(i) for i in f]) if len(f) else np.zeros((0, 3), np.int64)
    vals = []
    for fun in fields:
        V = fun.function_space
        v2d = _vertex_to_dof(V)
        bs = V.dofmap.index_map_bs
        arr = fun.x.array.reshape(-1, bs)
        vals.append(arr[v2d[verts]] if len(f) else np.zeros((0, 3, bs)))
    comm = msh.comm
    parts = comm.gather((X, *vals), root=0)
    if comm.rank != 0:
        return tuple(None for _ in range(1 + len(fields)))
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(1 + len(fields)))


def pad_pressure_png(msh, facets, u1, p1, axes, path: Path, *, title: str = "",
                     symmetry_normal=None) -> None:
    """Contact pressure (kPa, ``p1``: P1 Function) on the deformed surface ``facets``, projected
    on the plane spanned by ``axes`` (e.g. the plate plane), with a colour bar. A half model
    (``symmetry_normal``: its plane through the origin) is drawn with its mirror image.
    Collective."""
    X, U, P = surface_triangles(msh, facets, [u1, p1])
    if msh.comm.rank != 0:
        return
    if symmetry_normal is not None:
        e = np.asarray(symmetry_normal, dtype=float) / np.linalg.norm(symmetry_normal)
        x = X + U
        X = np.concatenate([x, x - 2.0 * (x @ e)[..., None] * e])
        U = np.zeros_like(X)
        P = np.concatenate([P, P])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    a1, a2 = (np.asarray(a, dtype=float) for a in axes)
    x = (X + U).reshape(-1, 3)
    p = P.reshape(-1)
    s, t = x @ a1, x @ a2
    tri = np.arange(len(s)).reshape(-1, 3)
    fig, ax = plt.subplots(figsize=(6, 5), dpi=120)
    vmax = max(float(np.max(p)) if len(p) else 0.0, 1e-9)
    tc = ax.tripcolor(Triangulation(s, t, tri), p, shading="gouraud", cmap="inferno",
                      vmin=0.0, vmax=vmax)
    ax.triplot(Triangulation(s, t, tri), lw=0.15, color="0.6", alpha=0.5)
    cb = fig.colorbar(tc, ax=ax)
    cb.set_label("contact pressure (kPa)")
    ax.set_aspect("equal")
    ax.set_xlabel("along the finger axis, in the plate plane (mm)")
    ax.set_ylabel("across the finger (mm)")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)

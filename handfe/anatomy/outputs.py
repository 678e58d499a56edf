"""Outputs of a meshed hand: XDMF mesh + tags, anatomy.json, quality.json, hand.png."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from handfe.anatomy.meshing import REGIONS, HandModel
from handfe.kinematics import joint_table

REGION_COLOURS = {"thumb": "#d62728", "index": "#ff7f0e", "middle": "#2ca02c",
                  "ring": "#1f77b4", "little": "#9467bd", "palm": "#c8a27c"}


def anatomy_dict(model: HandModel) -> dict:
    """Bone frames, bone ellipsoids, joints, ligaments and insertions (posed world frame, mm)."""
    sk = model.skeleton
    if sk is None:  # imported surfaces: no kinematic model
        return {"units": "mm", "imported": model.quality.get("imported"),
                "digits": list(model.digits), "level": model.level,
                "bones": {b: {"surface_tag": model.tags[f"bone_{b}"]} for b in model.bones},
                "tags": model.tags, "groups": {k: list(v) for k, v in model.groups.items()},
                "note": "imported model: bone frames, ligaments and insertions need a skeleton "
                        "registered to the scans (not done by the import path)"}
    kept = set(model.bones)
    bones = {}
    for name, b in sk.bones.items():
        if name not in kept:
            continue
        e = b.ellipsoid
        bones[name] = {"digit": b.digit, "segment": b.segment, "parent_joint": b.parent_joint,
                       "frame": b.frame.matrix().tolist(), "centre_mm": e.c.tolist(),
                       "axes": e.R.tolist(), "semi_axes_mm": e.s.tolist(),
                       "surface_tag": model.tags[f"bone_{name}"]}
    table = joint_table()
    joints = {}
    for j, c in sk.joint_centres.items():
        dofs = {d.name: {"value": model.skeleton.pose[d.name], "unit": d.unit, "min": d.min,
                         "max": d.max} for d in table.values() if d.joint == j}
        joints[j] = {"centre_mm": np.asarray(c).tolist(), "dofs": dofs}
    joints["wrist"] = {"centre_mm": sk.hand_frame.o.tolist(),
                       "dofs": {d.name: {"value": model.skeleton.pose[d.name], "unit": d.unit,
                                         "min": d.min, "max": d.max}
                                for d in table.values() if d.joint == "wrist"}}
    return {
        "units": "mm, N, degrees",
        "frame": "world = forearm frame; hand frame: x radial, y distal, z palmar (right hand)",
        "subject": model.skeleton.subject.subject, "subject_file": model.skeleton.subject.source,
        "pose": model.skeleton.pose.source, "angles": model.skeleton.pose.as_dict(),
        "digits": list(model.digits), "level": model.level,
        "hand_frame": sk.hand_frame.matrix().tolist(),
        "bones": bones, "joints": joints,
        "ligaments": model.ligaments, "insertions": model.insertions,
        "tags": model.tags, "groups": {k: list(v) for k, v in model.groups.items()},
    }


def render_png(model: HandModel, path: Path) -> None:
    """Off-screen palmar view of the outer skin coloured by region (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    surf = model.surface
    P = (model.skeleton.hand_frame.inverse_apply(surf.points) if model.skeleton is not None
         else surf.points)  # hand frame: palmar view from +z
    tri = surf.triangles
    T = P[tri]
    n = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    n /= np.linalg.norm(n, axis=1)[:, None] + 1e-30
    order = np.argsort(T[:, :, 2].mean(axis=1))  # far (small z) first
    region = (surf.codes // 10) % 10 - 1
    shade = 0.45 + 0.55 * np.abs(n[:, 2])
    base = np.array([to_rgb(REGION_COLOURS[REGIONS[r]]) for r in region])
    colours = np.clip(base * shade[:, None], 0, 1)
    fig, ax = plt.subplots(figsize=(6, 7.5), dpi=110)
    pc = PolyCollection(T[order][:, :, :2], facecolors=colours[order], edgecolors="none")
    ax.add_collection(pc)
    ax.set_xlim(P[:, 0].min() - 5, P[:, 0].max() + 5)
    ax.set_ylim(P[:, 1].min() - 5, P[:, 1].max() + 5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm, radial)")
    ax.set_ylabel("y (mm, distal)")
    q = model.quality
    who = model.skeleton.subject.subject if model.skeleton is not None else "imported"
    ax.set_title(f"{who} palmar view - {q.get('cells', 0)} tets "
                 f"({model.level}), {q.get('hand_volume_cm3', 0):.0f} cm$^3$", fontsize=9)
    present = sorted({REGIONS[r] for r in np.unique(region)}, key=REGIONS.index)
    ax.legend(handles=[Patch(color=REGION_COLOURS[r], label=r) for r in present],
              loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_outputs(model: HandModel, out_dir: str | Path) -> dict[str, Path]:
    """Write ``hand.xdmf`` (mesh, cell tags, facet tags), ``anatomy.json``, ``quality.json`` and
    ``hand.png`` into ``out_dir``. Collective on the mesh communicator; rank 0 writes the JSON
    and PNG files."""
    from dolfinx.io import XDMFFile

    out = Path(out_dir)
    comm = model.mesh.comm
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    comm.barrier()
    paths = {"xdmf": out / "hand.xdmf", "anatomy": out / "anatomy.json",
             "quality": out / "quality.json", "png": out / "hand.png"}
    msh = model.mesh
    msh.topology.create_connectivity(msh.topology.dim - 1, msh.topology.dim)
    with XDMFFile(comm, str(paths["xdmf"]), "w") as xdmf:
        xdmf.write_mesh(msh)
        xdmf.write_meshtags(model.cell_tags)
        xdmf.write_meshtags(model.facet_tags)
    if comm.rank == 0:
        paths["anatomy"].write_text(json.dumps(anatomy_dict(model), indent=1))
        paths["quality"].write_text(json.dumps(model.quality, indent=1))
        render_png(model, paths["png"])
    comm.barrier()
    return paths

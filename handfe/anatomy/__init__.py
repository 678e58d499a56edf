"""Parametric hand anatomy: subject tables, forward kinematics, posed OCC geometry, gmsh
meshing and outputs. Heavy modules (gmsh, dolfinx, matplotlib, trimesh) are imported lazily.

Public API::

    load_subject(subject_dir) -> Anthropometry
    build_skeleton(subject, pose) -> Skeleton                 # forward kinematics, no meshing
    build_hand(subject, pose, *, digits=None, level="reduced", comm=MPI.COMM_WORLD,
               skip_far=None) -> HandModel                # level: coarse|reduced|default|fine
    write_outputs(model, out_dir) -> dict[str, Path]
"""

from __future__ import annotations

from typing import Any

from handfe.anatomy.skeleton import Skeleton, build_skeleton
from handfe.anatomy.subject import Anthropometry, default_subject, load_subject

__all__ = ["Anthropometry", "Skeleton", "build_skeleton", "default_subject", "load_subject",
           "build_hand", "write_outputs", "HandModel"]


def __getattr__(name: str) -> Any:
    if name in ("build_hand", "HandModel", "tag_names", "LEVELS"):
        from handfe.anatomy import meshing
        return getattr(meshing, name)
    if name == "write_outputs":
        from handfe.anatomy.outputs import write_outputs
        return write_outputs
    raise AttributeError(name)

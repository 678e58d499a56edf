"""Whole-hand grasp workflows (issue 6): a subject, a grasp and a loading mode in, per-region
contact pressure and area, fields and pictures out.

Public API::

    load_workflow(path_or_name) -> Workflow
    run_workflow(workflow, *, mesh=None, out_dir=None, comm=MPI.COMM_WORLD, materials=None,
                 muscle_scale=None, loading=None, progress=True) -> GraspResult
"""

from __future__ import annotations

from typing import Any

from handfe.grasp.config import GraspSpec, ObjectSpec, Workflow, load_workflow

__all__ = ["GraspSpec", "ObjectSpec", "Workflow", "load_workflow", "run_workflow", "GraspResult"]


def __getattr__(name: str) -> Any:
    if name in ("run_workflow", "GraspResult"):
        from handfe.grasp import scene
        return getattr(scene, name)
    raise AttributeError(name)

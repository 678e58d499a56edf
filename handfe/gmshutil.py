"""One gmsh session per process, shared by every mesher (hand, fingertip, mesh cache, STL
import). Kept below both ``handfe.anatomy`` and ``handfe.meshcache`` so that neither imports
the other for it."""

from __future__ import annotations

_GMSH_READY = False


def ensure_gmsh(gmsh) -> None:
    """Initialise gmsh once per process (gmsh 4.8 has no ``isInitialized()``): every module that
    meshes goes through this and :func:`release_gmsh`, so that one finalising gmsh (the
    fingertip scene did) does not leave the others calling into a finalised library."""
    global _GMSH_READY
    if not _GMSH_READY:
        gmsh.initialize(readConfigFiles=False)
        _GMSH_READY = True


def release_gmsh(gmsh) -> None:
    """Finalise gmsh; the next :func:`ensure_gmsh` initialises it afresh. Every mesher calls it
    when done: gmsh options are global and outlive ``gmsh.model.remove()`` (the hand's
    ``Mesh.MeshSizeMax`` once capped a later mesh's elements), and a failed HXT run leaves
    gmsh 4.8 unable to mesh anything in the same session (every later model comes back
    empty)."""
    global _GMSH_READY
    try:
        gmsh.finalize()
    except Exception:  # already unusable: nothing more to release
        pass
    _GMSH_READY = False

"""On-disk cache of gmsh meshes (rank 0 only), shared by the fingertip and the hand.

The OCC booleans and the 3D meshing cost 5-8 s for a fingertip and 25-50 s per hand posture,
and a grasp's retries or a sensitivity study mesh the same inputs again and again. A mesh is
written once to ``$HANDFE_CACHE_DIR`` (default ``~/.cache/handfe``) under ``meshes/`` and read
back (``gmsh.open``) on the next run with the same key; ``HANDFE_MESH_CACHE=0`` bypasses the
cache. The key hashes the mesher's inputs, the gmsh version and the source files (and data
tables) the mesh depends on, so any change to them misses. Files are written to a temporary
name and renamed, so concurrent runs never read a half-written file; a cache that cannot be
written is skipped, and an unreadable file is deleted and meshed afresh.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any


def cache_root() -> Path | None:
    """The cache folder, None if ``HANDFE_MESH_CACHE=0``."""
    if os.environ.get("HANDFE_MESH_CACHE", "1") == "0":
        return None
    return Path(os.environ.get("HANDFE_CACHE_DIR") or Path.home() / ".cache" / "handfe")


def files_digest(paths: Iterable[Path]) -> str:
    """SHA-256 over the names and contents of ``paths`` (sorted)."""
    h = hashlib.sha256()
    for p in sorted(Path(p) for p in paths):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def cache_path(kind: str, key: Any, sources: Iterable[Path]) -> Path | None:
    """``meshes/<kind>-<hash>.msh`` for the JSON-able (or ``str()``-able) ``key``, the gmsh
    version and the contents of ``sources``; None if the cache is off."""
    root = cache_root()
    if root is None:
        return None
    import gmsh

    blob = json.dumps([key, getattr(gmsh, "__version__", ""), files_digest(sources)],
                      sort_keys=True, default=str)
    return root / "meshes" / f"{kind}-{hashlib.sha256(blob.encode()).hexdigest()[:20]}.msh"


def open_cached(gmsh, path: Path | None) -> bool:
    """Load the cached mesh at ``path`` into gmsh (initialised). False if there is none or it
    cannot be read (the file is then deleted and gmsh re-initialised, ready to mesh)."""
    if path is None or not path.exists():
        return False
    from handfe.gmshutil import ensure_gmsh, release_gmsh

    try:
        gmsh.open(str(path))
        return True
    except Exception:  # unreadable (truncated, other format): mesh afresh
        with contextlib.suppress(OSError):
            path.unlink(missing_ok=True)
        release_gmsh(gmsh)
        ensure_gmsh(gmsh)
        gmsh.option.setNumber("General.Terminal", 0)
        return False


def write_atomically(path: Path, write: Any) -> None:
    """Call ``write(tmp_path)`` then rename the temporary file onto ``path``; any error (no
    space, read-only home, a gmsh write error) skips the cache: a cache never fails a run.
    The temporary name keeps ``path``'s suffix."""
    tmp = path.with_name(f".{path.stem}.{os.getpid()}{path.suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write(tmp)
        os.replace(tmp, path)
    except Exception:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def write_mesh(gmsh, path: Path | None) -> None:
    """Store gmsh's current mesh (binary .msh 4, physical groups and names included)."""
    if path is None:
        return

    def write(tmp: Path) -> None:
        gmsh.option.setNumber("Mesh.Binary", 1)
        gmsh.write(str(tmp))

    write_atomically(path, write)

"""Points as a legacy VTK file with point data: what meshio-based loaders (Blender's sequence
loader, ParaView) read as vector attributes (a ``velocity`` for motion blur), which no PLY reader
gives (PLY properties are scalars). Numpy only."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .hdf5 import atomic_path


def write_vtk_points(path, positions, vectors: dict, scalars: dict, *, title: str = "gaussfluids particles") -> Path:
    """A legacy VTK file (version 4.2, binary: big-endian float32 / int32) of points as vertex
    cells of an unstructured grid (the dataset kind every legacy reader takes, meshio included), with point data: ``vectors`` (name -> (N, 3)) and ``scalars`` (name -> (N,)). Atomic."""
    p = np.asarray(positions, np.float64)
    n = len(p)
    out = [f"# vtk DataFile Version 4.2\n{title[:250]}\nBINARY\nDATASET UNSTRUCTURED_GRID\nPOINTS {n} float\n".encode(),
           p.astype(">f4").tobytes(), f"\nCELLS {n} {2 * n}\n".encode(),
           np.stack([np.ones(n, ">i4"), np.arange(n, dtype=">i4")], 1).astype(">i4").tobytes(),
           f"\nCELL_TYPES {n}\n".encode(), np.ones(n, ">i4").tobytes(),  # 1 = VTK_VERTEX
           f"\nPOINT_DATA {n}\n".encode()]
    for name, v in vectors.items():
        out += [f"VECTORS {name} float\n".encode(), np.asarray(v, np.float64).reshape(n, 3).astype(">f4").tobytes(), b"\n"]
    for name, v in scalars.items():
        out += [f"SCALARS {name} float 1\nLOOKUP_TABLE default\n".encode(),
                np.asarray(v, np.float64).reshape(n).astype(">f4").tobytes(), b"\n"]
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_bytes(b"".join(out))
    return Path(path)


__all__ = ["write_vtk_points"]

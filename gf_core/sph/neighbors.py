"""Fixed-radius and K-nearest neighbour search on a uniform grid: each query looks only at its 27
surrounding cells, no O(N^2) step. Two implementations with the same results: the native hashed
grid (``native/csrc/sph/sim_cpu.cpp`` for CPU pairs, ``sph_cpu.cpp`` / ``sph_cuda.cu`` for K-nearest), used by
default where it is built, and a vectorised torch grid (cell lists built by sorting), the
reference, which also serves CUDA tensors for pairs.
"""

from __future__ import annotations

import torch

# cells (cx+i, cy+j, cz-1..cz+1) are consecutive keys: 9 ranges cover the 27 cells
_OFFSETS = torch.tensor([[i, j, -1] for i in (-1, 0, 1) for j in (-1, 0, 1)], dtype=torch.int64)


def _use_native(backend: str, x: torch.Tensor) -> bool:
    if backend not in ("auto", "native", "torch"):
        raise ValueError(f"unknown neighbour backend {backend!r} (auto, native, torch)")
    if backend == "torch":
        return False
    from .. import native

    ok = x.device.type == "cpu" and native.available()
    if backend == "native" and not ok:
        raise RuntimeError(f"native neighbour lists run on CPU tensors with the native extension built "
                           f"({x.device.type} tensor; {native.unavailable_reason() or 'built'})")
    return ok


def build_grid(y: torch.Tensor, radius: float) -> list:
    """The native grid over ``y`` (cells of size ``radius``), to pass to ``neighbor_lists`` again
    and again while ``y`` does not move (e.g. a container's wall particles)."""
    from .. import native

    if not radius > 0:
        raise ValueError(f"neighbour radius must be positive, got {radius}")
    return native.load().grid_build(y.detach().contiguous(), float(radius))


def neighbor_lists(x: torch.Tensor, radius: float, y: torch.Tensor | None = None, *, grid: list | None = None):
    """Native CPU neighbour lists in CSR form: (rowptr (N+1,), col (P,)) int64, the neighbours j of
    x_i (|x_i - y_j| < radius, j != i when ``y`` is None) in col[rowptr[i]:rowptr[i+1]],
    ascending. ``grid``: ``build_grid(y, radius)`` made beforehand (static ``y``)."""
    from .. import native

    if not radius > 0:
        raise ValueError(f"neighbour radius must be positive, got {radius}")
    same = y is None
    xc = x.detach().contiguous()
    yc = xc if same else y.detach().contiguous()  # the very same tensor when x is searched among itself
    return native.load().radius_pairs(xc, yc, [] if grid is None else grid, float(radius), same)


def csr_rows(rowptr: torch.Tensor) -> torch.Tensor:
    """The row index of every entry of a CSR list (the i of each pair)."""
    n = rowptr.shape[0] - 1
    return torch.repeat_interleave(torch.arange(n, device=rowptr.device), rowptr[1:] - rowptr[:-1])


def neighbor_pairs(x: torch.Tensor, radius: float, y: torch.Tensor | None = None, *,
                   include_self: bool = False, backend: str = "auto", chunk: int = 1 << 16):
    """Pairs (i, j) with |x_i - y_j| < radius. ``y`` defaults to ``x``; then i != j unless
    ``include_self``. Returns int64 index tensors (i sorted ascending) on x's device.
    ``backend``: "native" (CPU, ``neighbor_lists``; j ascending within each i), "torch" (the
    reference below, any device) or "auto" (native where it can)."""
    if not radius > 0:
        raise ValueError(f"neighbour radius must be positive, got {radius}")
    if x.shape[0] and _use_native(backend, x) and (y is None or y.device.type == "cpu"):
        if not torch.isfinite(x).all() or (y is not None and not torch.isfinite(y).all()):
            raise ValueError("neighbor_pairs: positions contain NaN or infinite values")
        if y is not None and y.dtype != x.dtype:
            y = y.to(x.dtype)
        rowptr, col = neighbor_lists(x, radius, y)
        i = csr_rows(rowptr)
        if include_self and y is None:  # the lists leave i out of its own row
            n = x.shape[0]
            ar = torch.arange(n)
            i, col = torch.cat([i, ar]), torch.cat([col, ar])
            order = torch.argsort(i * n + col)
            i, col = i[order], col[order]
        return i, col
    return neighbor_pairs_torch(x, radius, y, include_self=include_self, chunk=chunk)


def neighbor_pairs_torch(x: torch.Tensor, radius: float, y: torch.Tensor | None = None, *,
                         include_self: bool = False, chunk: int = 1 << 16):
    """The pure-torch ``neighbor_pairs`` (CPU and CUDA; the reference the native one is tested
    against)."""
    same = y is None
    y = x if same else y
    dev = x.device
    empty = torch.zeros(0, dtype=torch.int64, device=dev)
    if x.shape[0] == 0 or y.shape[0] == 0:
        return empty, empty
    if not radius > 0:
        raise ValueError(f"neighbour radius must be positive, got {radius}")
    lo = torch.minimum(x.min(0).values, y.min(0).values).detach()
    cell_y = torch.floor((y.detach() - lo) / radius).to(torch.int64)
    dims = cell_y.max(0).values + 3
    cell_x = torch.floor((x.detach() - lo) / radius).to(torch.int64)
    dims = torch.maximum(dims, cell_x.max(0).values + 3)

    def key(c):
        return ((c[..., 0] + 1) * dims[1] + (c[..., 1] + 1)) * dims[2] + (c[..., 2] + 1)

    ky = key(cell_y)
    ky_sorted, order = torch.sort(ky)
    offs = _OFFSETS.to(dev)
    out_i, out_j = [], []
    r2 = radius * radius
    for s in range(0, x.shape[0], chunk):  # bounded memory for very large queries
        cx = cell_x[s:s + chunk]
        nk = key(cx[:, None, :] + offs[None]).reshape(-1)           # (n * 9) row starts
        start = torch.searchsorted(ky_sorted, nk)
        end = torch.searchsorted(ky_sorted, nk + 2, right=True)
        cnt = end - start
        qi = torch.arange(s, s + cx.shape[0], device=dev).repeat_interleave(9)
        tot = int(cnt.sum())
        if tot == 0:
            continue
        ii = torch.repeat_interleave(qi, cnt)
        base = torch.repeat_interleave(start - (torch.cumsum(cnt, 0) - cnt), cnt)
        jj = order[base + torch.arange(tot, device=dev)]
        d = x[ii].detach() - y[jj].detach()
        keep = (d * d).sum(-1) < r2
        if same and not include_self:
            keep &= ii != jj
        out_i.append(ii[keep])
        out_j.append(jj[keep])
    if not out_i:
        return empty, empty
    i, j = torch.cat(out_i), torch.cat(out_j)
    perm = torch.argsort(i, stable=True)
    return i[perm], j[perm]


def knn(x: torch.Tensor, k: int, radius: float, y: torch.Tensor | None = None, *, backend: str = "auto",
        sorted: bool = True):
    """Up to ``k`` nearest neighbours within ``radius`` (paper Sec. 4.1.2 uses K = 64):
    (N, k) indices (-1 where fewer) and distances (inf where fewer), nearest first; ``y``
    defaults to ``x`` (then a point is not its own neighbour). ``backend``: "native" (the C++ /
    CUDA hashed grid of ``native/csrc/sph/``), "torch" (this module's vectorised grid, the reference)
    or "auto" (native when built for the device). Distances carry no gradient on the native
    path: callers that need one recompute them from the indices. ``sorted=False`` lets the
    native path skip ordering each row (the same neighbours, in no particular order)."""
    if backend not in ("auto", "native", "torch"):
        raise ValueError(f"unknown knn backend {backend!r} (auto, native, torch)")
    if not radius > 0:
        raise ValueError(f"neighbour radius must be positive, got {radius}")
    if not torch.isfinite(x).all() or (y is not None and not torch.isfinite(y).all()):
        raise ValueError("knn: positions contain NaN or infinite values")
    if backend != "torch":
        from .. import native

        ok = native.available() and (x.device.type == "cpu" or (x.device.type == "cuda" and native.has_cuda()))
        if ok and (x.device.type == "cpu" or k <= 128):
            yy = x if y is None else y
            return native.load().knn(x.detach().contiguous(), yy.detach().contiguous(), int(k), float(radius),
                                     y is None, bool(sorted))
        if backend == "native":
            raise RuntimeError(f"native knn unavailable for {x.device.type} tensors: {native.unavailable_reason()}")
    return knn_torch(x, k, radius, y)


def knn_torch(x: torch.Tensor, k: int, radius: float, y: torch.Tensor | None = None):
    """The pure-torch ``knn`` (the reference the native one is tested against)."""
    i, j = neighbor_pairs(x, radius, y)
    n = x.shape[0]
    yy = x if y is None else y
    d = (x[i] - yy[j]).norm(dim=-1)
    # sort by (i, d): row-major slots
    order = torch.argsort(d.detach(), stable=True)
    order = order[torch.argsort(i[order], stable=True)]  # by i, then by distance
    i, j, d = i[order], j[order], d[order]
    cnt = torch.bincount(i, minlength=n)
    start = torch.cumsum(cnt, 0) - cnt
    rank = torch.arange(i.numel(), device=x.device) - start[i]
    m = rank < k
    idx = torch.full((n, k), -1, dtype=torch.int64, device=x.device)
    dist = torch.full((n, k), float("inf"), dtype=x.dtype, device=x.device)
    idx[i[m], rank[m]] = j[m]
    dist[i[m], rank[m]] = d[m]
    return idx, dist

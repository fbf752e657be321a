"""Fixed-radius neighbour search on a uniform grid (cell lists built by sorting), vectorised in
torch for CPU and CUDA tensors. No O(N^2) step: each query looks only at its 27 surrounding cells.
"""

from __future__ import annotations

import torch

# cells (cx+i, cy+j, cz-1..cz+1) are consecutive keys: 9 ranges cover the 27 cells
_OFFSETS = torch.tensor([[i, j, -1] for i in (-1, 0, 1) for j in (-1, 0, 1)], dtype=torch.int64)


def neighbor_pairs(x: torch.Tensor, radius: float, y: torch.Tensor | None = None, *,
                   include_self: bool = False, chunk: int = 1 << 16):
    """Pairs (i, j) with |x_i - y_j| < radius. ``y`` defaults to ``x``; then i != j unless
    ``include_self``. Returns int64 index tensors (i sorted ascending) on x's device."""
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
    CUDA hashed grid of ``csrc/sph_*``), "torch" (this module's vectorised grid, the reference)
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
        from .render import native

        ok = native.available() and (x.device.type == "cpu" or (x.device.type == "cuda" and native.has_cuda()))
        if ok and (x.device.type == "cpu" or k <= 128):
            return native.knn(x, x if y is None else y, k, radius, y is None, sorted)
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

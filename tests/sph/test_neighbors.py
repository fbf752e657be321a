"""Neighbour search: the native hashed grid and the torch grid against brute force."""

import pytest
import torch

from gf_core.sph.neighbors import knn, knn_torch, neighbor_pairs
from gf_core import native


def brute_knn(x, k, r, y=None):
    same = y is None
    y = x if same else y
    d = torch.cdist(x.double(), y.double())
    if same:
        d.fill_diagonal_(float("inf"))
    d = torch.where(d < r, d, torch.full_like(d, float("inf")))
    # nearest first, ties by index (a stable sort of the index order)
    dist, idx = torch.sort(d, dim=1, stable=True)
    dist, idx = dist[:, :k], idx[:, :k]
    if dist.shape[1] < k:  # fewer points than k
        pad = k - dist.shape[1]
        dist = torch.cat([dist, torch.full((dist.shape[0], pad), float("inf"), dtype=dist.dtype)], 1)
        idx = torch.cat([idx, torch.zeros((idx.shape[0], pad), dtype=idx.dtype)], 1)
    idx = torch.where(torch.isfinite(dist), idx, torch.full_like(idx, -1))
    return idx, dist


CASES = {
    "random": lambda g: torch.rand(700, 3, generator=g),
    "lattice": lambda g: torch.stack(torch.meshgrid(*[torch.arange(8.0)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.1
    + 1e-4 * torch.rand(512, 3, generator=g),
    "one": lambda g: torch.rand(1, 3, generator=g),
    "coincident": lambda g: torch.cat([torch.zeros(5, 3), torch.rand(50, 3, generator=g)]),
    "far_outside": lambda g: torch.cat([torch.rand(200, 3, generator=g), torch.tensor([[1e5, -3e4, 7e3]])]),
}


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("backend", ["torch", "native"])
@pytest.mark.parametrize("k", [1, 8, 64])
def test_knn_matches_brute_force(case, backend, k):
    g = torch.Generator().manual_seed(1)
    x = CASES[case](g).double()  # float64: near-ties order the same way as the brute force
    r = 0.23
    idx, dist = knn(x, k, r, backend=backend)
    idx32, dist32 = knn(x.float(), k, r, backend=backend)
    assert torch.equal(torch.isfinite(dist32), torch.isfinite(dist))
    assert torch.allclose(dist32[torch.isfinite(dist32)].double(), dist[torch.isfinite(dist)], atol=1e-6)
    bi, bd = brute_knn(x, k, r)
    assert idx.shape == (x.shape[0], k) and dist.shape == (x.shape[0], k)
    fin = torch.isfinite(bd)
    assert torch.equal(torch.isfinite(dist), fin)            # the same number of neighbours per row
    assert torch.equal(idx == -1, ~fin)                       # padding
    assert torch.allclose(dist[fin].double(), bd[fin], atol=1e-6)
    if case != "coincident":  # coincident points tie at distance 0: any order of them is right
        assert torch.equal(idx[fin], bi[fin])


@pytest.mark.parametrize("backend", ["torch", "native"])
def test_knn_between_two_sets_and_empty(backend):
    g = torch.Generator().manual_seed(2)
    x, y = torch.rand(300, 3, generator=g), torch.rand(400, 3, generator=g)
    idx, dist = knn(x, 16, 0.2, y, backend=backend)
    bi, bd = brute_knn(x, 16, 0.2, y)
    fin = torch.isfinite(bd)
    assert torch.equal(idx[fin], bi[fin]) and torch.equal(idx == -1, ~fin)
    e_idx, e_dist = knn(torch.zeros(0, 3), 4, 0.1, backend=backend)
    assert e_idx.shape == (0, 4) and e_dist.shape == (0, 4)


def test_knn_refuses_nan_rows():
    x = torch.rand(10, 3)
    x[3, 1] = float("nan")
    for backend in ("torch", "native"):
        with pytest.raises(ValueError, match="NaN"):
            knn(x, 4, 0.5, backend=backend)


def test_native_knn_is_used_by_default():
    assert native.available(), native.unavailable_reason()
    x = torch.rand(100, 3)
    a = knn(x, 8, 0.3)
    b = knn_torch(x, 8, 0.3)
    assert torch.equal(torch.isfinite(a[1]), torch.isfinite(b[1]))


def test_neighbor_pairs_match_brute_force():
    g = torch.Generator().manual_seed(3)
    x = torch.rand(400, 3, generator=g)
    i, j = neighbor_pairs(x, 0.15)
    d = torch.cdist(x, x)
    bi, bj = torch.nonzero((d < 0.15) & ~torch.eye(400, dtype=torch.bool), as_tuple=True)
    assert set(zip(i.tolist(), j.tolist())) == set(zip(bi.tolist(), bj.tolist()))

"""Pure-torch reference renderer: the oracle for every other backend.

Vectorised and tiled, runs on any torch device, differentiable through autograd (so
``torch.autograd.gradcheck`` in float64 checks it). The math, in order:

1. ``project``: per Gaussian (paper Sec. 3.1; Zwicker et al. 2001 EWA splatting; 3DGS):
   t = R_w2c p + t_w2c;  Sigma = R(q) S S^T R(q)^T;  J = d(pixel)/d(t) (x/z, y/z clamped to
   1.3x the image extent);  Sigma' = J R_w2c Sigma R_w2c^T J^T + 0.3 I;  conic = Sigma'^-1;
   colour = SH(dir) + 0.5 clamped at 0;  radius = ceil(k sqrt(lambda_max(Sigma'))) with
   k = sqrt(2 ln(opacity / min_alpha)): beyond it the splat's alpha is below ``min_alpha``.
   Done in float64 whatever the input dtype (large or very anisotropic Gaussians would lose the
   2D covariance determinant to cancellation in float32).
2. ``rasterize``: per pixel, front to back (paper Eq. 3):
   C = sum_k G_k alpha_k c_k prod_{j<k}(1 - G_j alpha_j) + T_final * background,
   skipping splats with alpha < min_alpha at that pixel and stopping before the transmittance
   drops below 1e-4.
"""

from __future__ import annotations

import math

import torch

from .constants import (ALPHA_MAX, FRUSTUM_SLACK, LOW_PASS, SH_C0, SH_C1, SH_C2, SH_C3,
                        TRANSMITTANCE_MIN)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions (w, x, y, z), normalised here (a zero quaternion gives identity)."""
    n2 = (q * q).sum(-1, keepdim=True)
    q = q * torch.rsqrt(torch.clamp_min(n2, 1e-24))
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(q.shape[:-1] + (3, 3))


def sh_basis(d: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis values (N, (degree+1)^2) for unit directions d (N, 3)."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree > 0:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree > 2:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, -1)


def project(means, scales, quats, opacities, sh, viewmat, intr, width: int, height: int, *,
            near: float, min_alpha: float, sh_degree: int):
    """Per-Gaussian projection. Returns means2d (N,2), conics (N,3), depths (N,), colors (N,C),
    radii (N,) int32 (0 = not drawn), all zero for culled Gaussians."""
    dt = means.dtype
    f64 = torch.float64
    p, s, q = means.to(f64), scales.to(f64), quats.to(f64)
    Rw = viewmat[:3, :3].to(device=means.device, dtype=f64)
    tw = viewmat[:3, 3].to(device=means.device, dtype=f64)
    fx, fy, cx, cy = [float(v) for v in intr]
    t = p @ Rw.T + tw
    tx, ty, tz = t.unbind(-1)
    in_front = torch.isfinite(tz) & (tz >= near)
    z = torch.where(in_front, tz, torch.ones_like(tz))  # safe denominator for culled ones

    R = quat_to_rotmat(q)
    M = R * s[:, None, :]
    Sigma = M @ M.transpose(1, 2)
    rx = torch.clamp(tx / z, -FRUSTUM_SLACK * cx / fx, FRUSTUM_SLACK * (width - cx) / fx)
    ry = torch.clamp(ty / z, -FRUSTUM_SLACK * cy / fy, FRUSTUM_SLACK * (height - cy) / fy)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * rx / z, zero, fy / z, -fy * ry / z], -1).reshape(-1, 2, 3)
    T = J @ Rw
    cov = T @ Sigma @ T.transpose(1, 2)
    a = cov[:, 0, 0] + LOW_PASS
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + LOW_PASS
    det = a * c - b * b
    ok = in_front & (det > 0) & torch.isfinite(det)
    det = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], -1)
    u = fx * tx / z + cx
    v = fy * ty / z + cy
    means2d = torch.stack([u, v], -1)

    # colour from SH along the viewing direction
    campos = -(Rw.T @ tw)
    dirs = p - campos
    dirs = dirs / torch.clamp_min(dirs.norm(dim=-1, keepdim=True), 1e-12)
    basis = sh_basis(dirs, sh_degree)
    k = basis.shape[-1]
    colors = torch.clamp_min((basis[:, :, None] * sh[:, :k, :].to(f64)).sum(1) + 0.5, 0.0)

    with torch.no_grad():
        op = opacities.detach().to(f64)
        ok = ok & (op > min_alpha)
        kappa = torch.sqrt(2.0 * torch.log(torch.clamp_min(op, min_alpha) / min_alpha))
        lam = 0.5 * (a + c) + torch.sqrt(torch.clamp_min(0.25 * (a - c) ** 2 + b * b, 0.0))
        radius = torch.ceil(kappa * torch.sqrt(lam))
        radius = torch.where(ok & torch.isfinite(radius), radius, torch.zeros_like(radius))
        # drop splats whose box misses the image entirely (pixel j has its centre at j + 0.5)
        off = ((u + radius - 0.5 < 0) | (u - radius - 0.5 > width - 1)
               | (v + radius - 0.5 < 0) | (v - radius - 0.5 > height - 1))
        radius = torch.where(off | (radius <= 0), torch.zeros_like(radius), radius)
        radii = torch.clamp(radius, max=2.0 ** 30).to(torch.int32)
    vis = (radii > 0)[:, None]
    return (torch.where(vis, means2d, 0.0).to(dt), torch.where(vis, conics, 0.0).to(dt),
            torch.where(vis[:, 0], tz, 0.0).to(dt), torch.where(vis, colors, 0.0).to(dt), radii)


def tile_ranges(means2d, radii, width: int, height: int, tile: int):
    """Inclusive tile rectangles (x0, y0, x1, y1) per Gaussian, and a visibility mask."""
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    r = radii.to(torch.float64)
    u, v = means2d[:, 0].detach().to(torch.float64), means2d[:, 1].detach().to(torch.float64)
    x0 = torch.floor((u - r - 0.5) / tile).clamp(0, tiles_x - 1)
    x1 = torch.floor((u + r - 0.5) / tile).clamp(0, tiles_x - 1)
    y0 = torch.floor((v - r - 0.5) / tile).clamp(0, tiles_y - 1)
    y1 = torch.floor((v + r - 0.5) / tile).clamp(0, tiles_y - 1)
    rect = torch.stack([x0, y0, x1, y1], -1).to(torch.int64)
    return rect, radii > 0


def bin_gaussians(means2d, depths, radii, width: int, height: int, tile: int):
    """Tile/Gaussian pairs sorted by tile, then depth (stable). Returns (offsets, ids)."""
    dev = means2d.device
    n = means2d.shape[0]
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    rect, vis = tile_ranges(means2d, radii, width, height, tile)
    order = torch.sort(depths.detach(), stable=True).indices
    rank = torch.empty(n, dtype=torch.int64, device=dev)
    rank[order] = torch.arange(n, device=dev)
    gid = torch.nonzero(vis).flatten()
    rect = rect[gid]
    wx = rect[:, 2] - rect[:, 0] + 1
    wy = rect[:, 3] - rect[:, 1] + 1
    cnt = wx * wy
    pair_g = torch.repeat_interleave(gid, cnt)
    start = torch.cumsum(cnt, 0) - cnt
    local = torch.arange(int(cnt.sum()), device=dev) - torch.repeat_interleave(start, cnt)
    wx_r = torch.repeat_interleave(wx, cnt)
    tx = torch.repeat_interleave(rect[:, 0], cnt) + local % wx_r
    ty = torch.repeat_interleave(rect[:, 1], cnt) + local // wx_r
    tile_id = ty * tiles_x + tx
    key = tile_id * max(n, 1) + rank[pair_g]
    perm = torch.sort(key).indices
    ids = pair_g[perm]
    counts = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64, device=dev)
    offsets[1:] = torch.cumsum(counts, 0)
    return offsets, ids


def rasterize(means2d, conics, opacities, features, background, radii, depths, width: int,
              height: int, *, tile: int, min_alpha: float, max_elements: int = 1 << 22):
    """Front-to-back compositing of ``features`` (N, F). Returns (image (H, W, F), T_final (H, W))."""
    dev, dt = means2d.device, means2d.dtype
    F = features.shape[1]
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    offsets, ids = bin_gaussians(means2d, depths, radii, width, height, tile)
    counts = (offsets[1:] - offsets[:-1]).cpu()
    P = tile * tile
    py, px = torch.meshgrid(torch.arange(tile, device=dev), torch.arange(tile, device=dev), indexing="ij")
    pix = torch.stack([px.flatten(), py.flatten()], -1).to(dt) + 0.5  # pixel centres in a tile
    out_tiles, T_tiles = [], []
    n_tiles = tiles_x * tiles_y
    t0 = 0
    while t0 < n_tiles:
        # a chunk of tiles whose padded work fits in max_elements
        t1, kmax = t0, 0
        while t1 < n_tiles:
            k_new = max(kmax, int(counts[t1]))
            if t1 > t0 and (t1 - t0 + 1) * P * max(k_new, 1) > max_elements:
                break
            kmax, t1 = k_new, t1 + 1
        tid = torch.arange(t0, t1, device=dev)
        origin = torch.stack([(tid % tiles_x) * tile, (tid // tiles_x) * tile], -1).to(dt)
        xy = origin[:, None, :] + pix[None]                       # (Tc, P, 2)
        if kmax == 0:
            out_tiles.append(background.to(dt).expand(t1 - t0, P, F))
            T_tiles.append(torch.ones(t1 - t0, P, dtype=dt, device=dev))
            t0 = t1
            continue
        slot = torch.arange(kmax, device=dev)
        pos = offsets[t0:t1, None] + slot[None]                    # (Tc, K)
        valid = slot[None] < (offsets[t0 + 1:t1 + 1] - offsets[t0:t1])[:, None]
        g = torch.where(valid, ids[pos.clamp(max=max(ids.numel() - 1, 0))], 0)
        d = means2d[g][:, None, :, :] - xy[:, :, None, :]          # (Tc, P, K, 2): mean - pixel
        con = conics[g][:, None]                                   # (Tc, 1, K, 3)
        power = (-0.5 * (con[..., 0] * d[..., 0] ** 2 + con[..., 2] * d[..., 1] ** 2)
                 - con[..., 1] * d[..., 0] * d[..., 1])
        alpha = torch.clamp(opacities[g][:, None] * torch.exp(torch.clamp_max(power, 0.0)), max=ALPHA_MAX)
        keep = valid[:, None] & (power <= 0) & (alpha >= min_alpha)
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            t_incl = torch.cumprod(1 - alpha, -1)
            keep = keep & (t_incl >= TRANSMITTANCE_MIN)
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        one_minus = 1 - alpha
        T_excl = torch.cat([torch.ones_like(one_minus[..., :1]), torch.cumprod(one_minus, -1)[..., :-1]], -1)
        w = alpha * T_excl                                          # (Tc, P, K)
        T_final = T_excl[..., -1] * one_minus[..., -1]
        col = torch.einsum("tpk,tkf->tpf", w, features[g])
        out_tiles.append(col + T_final[..., None] * background.to(dt))
        T_tiles.append(T_final)
        t0 = t1
    img = torch.cat(out_tiles, 0).reshape(tiles_y, tiles_x, tile, tile, F)
    img = img.permute(0, 2, 1, 3, 4).reshape(tiles_y * tile, tiles_x * tile, F)[:height, :width]
    T = torch.cat(T_tiles, 0).reshape(tiles_y, tiles_x, tile, tile)
    T = T.permute(0, 2, 1, 3).reshape(tiles_y * tile, tiles_x * tile)[:height, :width]
    if not img.requires_grad and torch.is_grad_enabled():
        # nothing was drawn: keep the outputs in the graph (with zero gradients), like native
        inputs = [t for t in (means2d, conics, opacities, features) if t.requires_grad]
        if inputs:
            zero = sum(t.sum() for t in inputs) * 0.0
            img, T = img + zero, T + zero
    return img, T

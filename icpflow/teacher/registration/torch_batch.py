"""Step 6's batch registration in torch (padded batch, ``torch.cdist``; meant for GPUs, runs on CPU): the same
algorithm and outputs as ``icpflow.teacher.registration.cpu`` (point-to-point only), float64 throughout."""

from __future__ import annotations

import numpy as np

from icpflow.teacher.config import ICPConfig


def register_batch_torch(movings, fixeds, inits, params: ICPConfig, device=None):
    """Padded batched ICP in torch: same algorithm as the cpu backend (float64 throughout); returns (transforms,
    errors, IoU ratios, iterations, symmetric errors) as ``register_batch_cpu``'s first four and its symmetric
    errors."""
    import torch

    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    n_pairs = len(movings)
    m_max = max(1, max(len(m) for m in movings))
    f_max = max(1, max(len(f) for f in fixeds))
    far = 1e6  # padding coordinate: never a neighbour of a real point, never within any threshold
    mov = torch.full((n_pairs, m_max, 3), far, dtype=torch.float64)
    fix = torch.full((n_pairs, f_max, 3), -far, dtype=torch.float64)
    m_mask = torch.zeros((n_pairs, m_max), dtype=torch.bool)
    f_mask = torch.zeros((n_pairs, f_max), dtype=torch.bool)
    for p, (m, f) in enumerate(zip(movings, fixeds)):
        mov[p, : len(m)] = torch.from_numpy(m)
        fix[p, : len(f)] = torch.from_numpy(f)
        m_mask[p, : len(m)] = True
        f_mask[p, : len(f)] = True
    mov, fix, m_mask, f_mask = mov.to(device), fix.to(device), m_mask.to(device), f_mask.to(device)
    init = torch.from_numpy(np.ascontiguousarray(inits)).to(device)

    def apply(transform, points):
        return points @ transform[:, :3, :3].transpose(1, 2) + transform[:, None, :3, 3]

    def nearest(query, points):
        # Chunked over pairs so that one distance block holds at most about 2**24 entries.
        step = max(1, 2**24 // (query.shape[1] * points.shape[1]))
        parts = [torch.cdist(query[b : b + step], points[b : b + step]).min(dim=2) for b in range(0, n_pairs, step)]
        return torch.cat([d for d, _ in parts]), torch.cat([j for _, j in parts])

    def mean_nn(query, q_mask, points):
        d, _ = nearest(query, points)
        mean = (d * q_mask).sum(1) / q_mask.sum(1).clamp(min=1)
        inliers = ((d < params.max_corr) & q_mask).sum(1)  # inlier distance = truncation
        return mean, inliers

    n_m, n_f = m_mask.sum(1), f_mask.sum(1)
    valid = (n_m > 0) & (n_f > 0)
    err_init, _ = mean_nn(apply(init, mov), m_mask, fix)
    transform = init.clone()
    active = valid.clone()
    prev_rmse = torch.full((n_pairs,), -1.0, dtype=torch.float64, device=device)  # negative: no previous
    iterations = torch.zeros(n_pairs, dtype=torch.long, device=device)
    for _ in range(params.max_iter):
        if not bool(active.any()):
            break
        d, j = nearest(apply(transform, mov), fix)
        w = ((d < params.max_corr) & m_mask).to(torch.float64)
        count = w.sum(1)
        active = active & (count >= 3)
        target = torch.gather(fix, 1, j[..., None].expand(-1, -1, 3))
        cw = count.clamp(min=1)[:, None]
        mean_m = (mov * w[..., None]).sum(1) / cw
        mean_f = (target * w[..., None]).sum(1) / cw
        h = ((mov - mean_m[:, None]) * w[..., None]).transpose(1, 2) @ (target - mean_f[:, None])
        if params.dof == "yaw":
            angle = torch.atan2(h[:, 0, 1] - h[:, 1, 0], h[:, 0, 0] + h[:, 1, 1])
            rotation = torch.eye(3, dtype=torch.float64, device=device).repeat(n_pairs, 1, 1)
            rotation[:, 0, 0], rotation[:, 0, 1] = torch.cos(angle), -torch.sin(angle)
            rotation[:, 1, 0], rotation[:, 1, 1] = torch.sin(angle), torch.cos(angle)
        else:
            u, _, vt = torch.linalg.svd(h)
            v = vt.transpose(1, 2)
            d_fix = torch.ones((n_pairs, 3), dtype=torch.float64, device=device)
            d_fix[:, 2] = torch.where(torch.linalg.det(v @ u.transpose(1, 2)) < 0, -1.0, 1.0)
            rotation = v @ torch.diag_embed(d_fix) @ u.transpose(1, 2)
        new = torch.eye(4, dtype=torch.float64, device=device).repeat(n_pairs, 1, 1)
        new[:, :3, :3] = rotation
        new[:, :3, 3] = mean_f - (rotation @ mean_m[..., None])[..., 0]
        transform = torch.where(active[:, None, None], new, transform)
        iterations += active.long()
        rmse = (((apply(new, mov) - target).square().sum(2) * w).sum(1) / count.clamp(min=1)).sqrt()
        active = active & ~((prev_rmse >= 0) & (prev_rmse - rmse <= params.rel_rmse * prev_rmse))
        prev_rmse = rmse
    err_fwd, _ = mean_nn(apply(transform, mov), m_mask, fix)
    worse = err_fwd >= err_init
    transform = torch.where(worse[:, None, None], init, transform)
    moved = torch.where(m_mask[..., None], apply(transform, mov), torch.full_like(mov, far))
    err_fwd, inl_fwd = mean_nn(moved, m_mask, fix)
    err_bwd, inl_bwd = mean_nn(torch.where(f_mask[..., None], fix, torch.full_like(fix, -far)), f_mask, moved)
    n_all = (n_m + n_f).to(torch.float64)
    iou = torch.minimum(inl_fwd / (n_all - inl_fwd), inl_bwd / (n_all - inl_bwd))
    error = torch.where(valid, torch.minimum(err_fwd, err_bwd), torch.full_like(err_fwd, float("inf")))
    symmetric = torch.where(valid, 0.5 * (err_fwd + err_bwd), torch.full_like(err_fwd, float("inf")))
    iou = torch.where(valid, iou, torch.zeros_like(iou))
    transform = torch.where(valid[:, None, None], transform, init)
    return (
        transform.cpu().numpy(),
        error.cpu().numpy(),
        iou.cpu().numpy(),
        iterations.cpu().numpy(),
        symmetric.cpu().numpy(),
    )

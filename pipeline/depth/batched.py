"""DST Poisson heights of a whole batch of normal maps on one torch device.

One code path for CPU and CUDA (the device of the tensors given): :func:`dst_divergence_torch`
builds :func:`pipeline.depth.poisson.poisson_dst`'s right-hand side for a batch of normals, and
:func:`dst_heights` solves it with ``torch.fft`` (the DST-II basis is the half-sample
antisymmetric extension, so an FFT of the extended ``(2H, 2W)`` right-hand side divided by the
same eigenvalues gives the same heights). The normals of a batch on the device:
:class:`pipeline.normals.batched.NearFieldBatched`; the fused CUDA kernel that does both steps
at once: :class:`pipeline.depth.gpu_dst.GPUDST`.
"""

from __future__ import annotations

import torch

__all__ = ["dst_heights", "dst_divergence_torch"]


def dst_divergence_torch(normals: torch.Tensor, mask: torch.Tensor, mm_per_px: float, max_slope: float = 20.0):
    """``(f (B, H, W), valid (B, H, W))``: ``poisson_dst``'s right-hand side for a batch of normals."""
    n = normals
    nz = n[..., 2]
    valid = mask & (nz > 0) & torch.isfinite(nz)
    safe = torch.where(valid, nz, torch.ones_like(nz))
    p = torch.where(valid, -n[..., 0] / safe, torch.zeros_like(nz))
    q = torch.where(valid, -n[..., 1] / safe, torch.zeros_like(nz))
    ok = torch.isfinite(p) & torch.isfinite(q)
    valid = valid & ok
    p = torch.where(ok, p, torch.zeros_like(p))
    q = torch.where(ok, q, torch.zeros_like(q))
    mag = torch.hypot(p, q)
    scale = torch.where(mag > max_slope, max_slope / torch.clamp(mag, min=torch.finfo(p.dtype).tiny),
                        torch.ones_like(mag))
    gc = p * scale * mm_per_px
    gr = -q * scale * mm_per_px
    ec = 0.5 * (gc[..., :, 1:] + gc[..., :, :-1])
    er = 0.5 * (gr[..., 1:, :] + gr[..., :-1, :])
    ecp = torch.cat([gc[..., :, :1], ec, gc[..., :, -1:]], dim=-1)
    erp = torch.cat([gr[..., :1, :], er, gr[..., -1:, :]], dim=-2)
    f = (ecp[..., :, 1:] - ecp[..., :, :-1]) + (erp[..., 1:, :] - erp[..., :-1, :])
    return f, valid


_EIG: dict = {}


def dst_heights(f: torch.Tensor) -> torch.Tensor:
    """Solve ``lap h = f`` (5-point, zero height half a pixel outside the image) for a batch
    ``f (B, H, W)`` by FFT on ``f``'s device: the antisymmetric extension to ``(2H, 2W)`` is
    periodic with the DST-II basis as its eigenvectors."""
    B, H, W = f.shape
    key = (H, W, f.device, f.dtype)
    if key not in _EIG:
        ky = 2.0 * torch.cos(torch.pi * torch.arange(2 * H, dtype=torch.float64) / H) - 2.0
        kx = 2.0 * torch.cos(torch.pi * torch.arange(W + 1, dtype=torch.float64) / W) - 2.0
        lam = ky[:, None] + kx[None, :]
        lam[0, 0] = 1.0  # the mean of an antisymmetric extension is 0: any value
        _EIG[key] = lam.to(device=f.device, dtype=f.dtype)
    ext = torch.cat([f, -f.flip(-1)], dim=-1)
    ext = torch.cat([ext, -ext.flip(-2)], dim=-2)  # (B, 2H, 2W), antisymmetric about the borders
    F = torch.fft.rfft2(ext)
    F = F / _EIG[key]
    F[:, 0, 0] = 0
    return torch.fft.irfft2(F, s=(2 * H, 2 * W))[:, :H, :W]

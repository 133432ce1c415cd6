"""Near-field normals of a whole batch of frames on one torch device.

One code path for CPU and CUDA (``device=``): the light field's factors are precomputed once
on the device (:class:`NearFieldBatched`, the same normal equations as
:class:`pipeline.normals.nearfield.NearFieldSolver` and :class:`pipeline.normals.fast.NearFieldFast`),
a batch of integer frames ``(B, P, H, W, C)`` is uploaded once, and normals, albedo,
residual and mask come out of a handful of batched tensor operations with no host
round trip in between. Their heights, on the same device: :mod:`pipeline.depth.batched`.

On the CPU the Numba path is faster per frame (memory traffic); this path is for GPUs,
where a batch of a few hundred frames amortises the launches (``iristac bench live --device
cuda``, ``iristac batch --device cuda``).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["NearFieldBatched"]


class NearFieldBatched:
    """Batched near-field photometric stereo on ``device``.

    Parameters
    ----------
    lights : ndarray, shape (P, C, H, W, 3)
        Per-pixel light vectors (one albedo group per camera channel).
    flat_field : ndarray, shape (P, C, H, W), optional
    max_condition : float
    albedo_iterations : int, optional
        As :class:`~pipeline.normals.fast.NearFieldFast` (None: 3 when the channels see
        different lights, else 0).
    device, dtype
        Torch device and float type (float32 default; float64 for references).
    """

    def __init__(self, lights, *, flat_field=None, max_condition: float = 1e3, albedo_iterations: int | None = None,
                 device="cpu", dtype=torch.float32):
        from pipeline.normals.fast import NearFieldFast

        L = np.asarray(lights, np.float64)
        if L.ndim != 5 or L.shape[-1] != 3:
            raise ValueError(f"NearFieldBatched: lights must be (P, C, H, W, 3), got {L.shape}")
        P, C, H, W, _ = L.shape
        self.P, self.C, self.shape = P, C, (H, W)
        self.device, self.dtype = torch.device(device), dtype
        # The factors, once, in float64 (the same as the Numba path's).
        ref = NearFieldFast(L.reshape(P * C, H, W, 3), groups=np.tile(np.arange(C), P), max_condition=max_condition,
                            albedo_iterations=albedo_iterations,
                            flat_field=None if flat_field is None else np.asarray(flat_field).reshape(P * C, H, W))
        self.iterations = ref.iterations
        M = H * W
        Lm = np.where(np.isfinite(L), L, 0.0).reshape(P, C, M, 3)
        Q = np.einsum("pcmi,pcmj->cmij", Lm, Lm)  # (C, M, 3, 3)
        A = Q.sum(0)
        det = np.linalg.det(A)
        inv = np.zeros_like(A)
        good = np.isfinite(det) & (det != 0)
        inv[good] = np.linalg.inv(A[good])
        t = dict(device=self.device, dtype=dtype)
        self.L = torch.as_tensor(Lm.transpose(0, 1, 3, 2), **t)  # (P, C, 3, M)
        self.Q = torch.as_tensor(Q.transpose(0, 2, 3, 1), **t)  # (C, 3, 3, M)
        self.inv = torch.as_tensor(inv.transpose(1, 2, 0), **t)  # (3, 3, M)
        self.valid0 = torch.as_tensor(ref.valid0, device=self.device)
        self.condition = torch.as_tensor(ref.condition_m, **t)
        self.invflat = None
        if flat_field is not None:
            f = np.asarray(flat_field, np.float64).reshape(P, C, M)
            self.invflat = torch.as_tensor(np.where(f > 0, 1.0 / np.where(f > 0, f, 1.0), 0.0), **t)

    def solve(self, frames, dark=None) -> dict[str, torch.Tensor]:
        """Normals of a batch ``frames (B, P, H, W, C)`` (numpy or tensor, any real dtype).

        Returns tensors on the device: ``normals (B, H, W, 3)``, ``albedo (B, H, W, C)``,
        ``residual (B, H, W)``, ``mask (B, H, W)`` bool.
        """
        x = torch.as_tensor(frames, device=self.device)
        B, P, H, W, C = x.shape
        if (P, C, (H, W)) != (self.P, self.C, self.shape):
            raise ValueError(f"NearFieldBatched.solve: frames must be (B, {self.P}, {self.shape[0]}, {self.shape[1]}, "
                             f"{self.C}), got {tuple(x.shape)}")
        I = x.to(self.dtype).permute(0, 1, 4, 2, 3).reshape(B, P, C, H * W)
        if dark is not None:
            I = I - torch.as_tensor(dark, device=self.device, dtype=self.dtype).permute(2, 0, 1).reshape(1, 1, C, -1)
        if self.invflat is not None:
            I = I * self.invflat
        r = torch.einsum("bpcm,pcim->bcim", I, self.L)  # per-group moments (B, C, 3, M)
        S = (I * I).sum(1)  # (B, C, M)
        b = torch.einsum("ijm,bjm->bim", self.inv, r.sum(1))
        tiny = torch.finfo(self.dtype).tiny
        for _ in range(self.iterations if self.C > 1 else 0):
            n = b / torch.clamp(b.norm(dim=1, keepdim=True), min=tiny)
            rho = self._albedo(r, n)
            mean = rho.mean(1, keepdim=True)
            ok = (rho > 0) & (mean > 0)
            rel = torch.where(ok, rho / torch.where(ok, mean, torch.ones_like(mean)), torch.ones_like(rho))
            A = torch.einsum("bcm,cijm->bijm", rel * rel, self.Q)
            b = _solve3(A, (r * rel[:, :, None]).sum(1))
        norm = b.norm(dim=1)
        n = b / torch.clamp(norm, min=tiny)[:, None]
        valid = self.valid0 & (norm > 0) & (n[:, 2] > 0)
        flat = torch.zeros_like(n)
        flat[:, 2] = 1.0
        n = torch.where(valid[:, None], n, flat)
        p = torch.einsum("bcim,bim->bcm", r, n)
        q = torch.clamp(torch.einsum("cijm,bim,bjm->bcm", self.Q, n, n), min=tiny)
        rho = torch.where(valid[:, None], p / q, torch.zeros_like(p))
        res = torch.sqrt(torch.clamp(S.sum(1) - (p * p / q).sum(1), min=0.0) / (P * C))
        res = torch.where(valid, res, torch.zeros_like(res))
        return {"normals": n.permute(0, 2, 1).reshape(B, H, W, 3), "albedo": rho.permute(0, 2, 1).reshape(B, H, W, C),
                "residual": res.reshape(B, H, W), "mask": valid.reshape(B, H, W)}

    def _albedo(self, r, n):
        p = torch.einsum("bcim,bim->bcm", r, n)
        q = torch.einsum("cijm,bim,bjm->bcm", self.Q, n, n)
        return p / torch.clamp(q, min=torch.finfo(self.dtype).tiny)


def _solve3(A: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``A^-1 y`` per pixel by the adjugate (``A (B, 3, 3, M)``, ``y (B, 3, M)``); singular -> 0."""
    a, b_, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c00 + b_ * c01 + c * c02
    adj = torch.stack([torch.stack([c00, c * h - b_ * i, b_ * f - c * e], 1),
                       torch.stack([c01, a * i - c * g, c * d - a * f], 1),
                       torch.stack([c02, b_ * g - a * h, a * e - b_ * d], 1)], 1)
    idet = torch.where(det != 0, 1.0 / torch.where(det != 0, det, torch.ones_like(det)), torch.zeros_like(det))
    return torch.einsum("bijm,bjm->bim", adj, y) * idet[:, None]

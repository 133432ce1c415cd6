"""Least squares for ``b = rho n`` with per-group (per-channel) albedo by alternation.

With one albedo the model ``I_k = b . L_k`` is linear. With an albedo per camera channel,
``I_k = rho_g(k) n . L_k`` is bilinear; we alternate: solve ``b`` jointly, estimate each
group's albedo given the normal, rescale each group's observations to the mean albedo, and
solve again. Each step is one linear solve, so the fast far-field path stays one matmul.
"""

from __future__ import annotations

from typing import Callable

import torch

from pipeline.normals import _torch as T


def solve_general(I: torch.Tensor, L: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted per-pixel normal equations; returns ``b`` ``(M, 3)`` and ``cond`` ``(M,)``."""
    A = T.gram(L, w)
    inv, _ = T.inverse3(A)
    b = torch.einsum("mij,mj->mi", inv, T.rhs(I, L, w))
    return b, T.condition_from_gram(A)


def alternate_albedo(I: torch.Tensor, L: torch.Tensor, w: torch.Tensor, groups: torch.Tensor | None,
                     num_groups: int, solve_b: Callable[[torch.Tensor], torch.Tensor],
                     iterations: int) -> torch.Tensor:
    """Solve ``b`` with ``solve_b(I)``, then refine for per-group albedo ``iterations`` times."""
    b = solve_b(I)
    if groups is None or num_groups < 2:
        return b
    for _ in range(iterations):
        norm = torch.linalg.vector_norm(b, dim=-1, keepdim=True)
        n = b / torch.where(norm > 0, norm, torch.ones_like(norm))
        rho = T.group_albedo(I, T.project(L, n), w, groups, num_groups)  # (M, G)
        mean = rho.mean(-1, keepdim=True)
        ok = rho > 0
        scale = torch.where(ok, mean / torch.where(ok, rho, torch.ones_like(rho)), torch.ones_like(rho))
        b = solve_b(I * scale.T[groups])
    return b

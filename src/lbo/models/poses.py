"""Headings in torch: the networks' and the torch filters' form of
:func:`lbo.core.angles.wrap_angle` (a module of its own, importing torch, so that
:mod:`lbo.models.features` stays free of it for numpy work, and TorchScript can compile these)."""

from __future__ import annotations

import math

import torch


def wrap_angle_torch(a: torch.Tensor) -> torch.Tensor:
    """Wrap angles to (-pi, pi], the same convention as :func:`lbo.core.angles.wrap_angle`."""
    return math.pi - torch.remainder(math.pi - a, 2 * math.pi)


def wrap_heading(p: torch.Tensor) -> torch.Tensor:
    """Poses or pose differences (..., 3) ``[x, y, psi]``, or states that start with one
    (..., n >= 3), with psi (column 2) wrapped to (-pi, pi]."""
    return torch.cat([p[..., :2], wrap_angle_torch(p[..., 2:3]), p[..., 3:]], -1)

"""The torch filters' one Kalman update (lbo.models.update): Joseph's covariance for any gain,
the inverse of S by LAPACK when run eagerly and by cofactors when traced, and every channel
held as the mask of ones."""

from __future__ import annotations

import pytest
import torch

from lbo.models.update import inverse_sym, inverse_sym2, inverse_sym3, joseph, masked_update


def _randn(gen: torch.Generator, *shape: int) -> torch.Tensor:
    return torch.randn(*shape, generator=gen, dtype=torch.float64)


def _spd(B: int, n: int, gen: torch.Generator) -> torch.Tensor:
    """B random symmetric positive-definite (n, n) matrices, float64."""
    a = _randn(gen, B, n, n)
    return a @ a.transpose(1, 2) + 0.1 * torch.eye(n, dtype=torch.float64)


@pytest.mark.parametrize("shape", ["identity", "shared", "per_row"])
def test_joseph_is_the_textbook_form_for_any_gain_not_only_the_optimal_one(shape):
    """Joseph's form is right for a gain that is off (a learned or rounded one), where the
    short form ``(I - K H) P`` is not: factored, it must stay the same polynomial in K."""
    gen = torch.Generator().manual_seed(0)
    B, n = 16, 3 if shape == "identity" else 5
    P, R = _spd(B, n, gen), _spd(B, 3, gen)
    H = {"identity": None, "shared": _randn(gen, 3, n), "per_row": _randn(gen, B, 3, n)}[shape]
    Hm = torch.eye(3, dtype=torch.float64) if H is None else H
    K = _randn(gen, B, n, 3)  # any gain
    z, y = _randn(gen, B, n), _randn(gen, B, 3)
    PHt = P @ Hm.transpose(-1, -2)
    z_new, P_new = joseph(z, P, PHt, K, y, R, H)
    A = torch.eye(n, dtype=torch.float64) - K @ Hm
    want = A @ P @ A.transpose(-1, -2) + K @ R @ K.transpose(-1, -2)
    torch.testing.assert_close(P_new, want, rtol=0, atol=1e-10)
    torch.testing.assert_close(z_new, z + (K @ y[..., None])[..., 0], rtol=0, atol=1e-12)
    assert torch.equal(P_new, P_new.transpose(-1, -2))
    short = A @ P  # ... which a gain that is off tells apart: the comparison can fail
    assert (short - want).abs().max() > 1e-3


@pytest.mark.parametrize("m", [2, 3])
def test_the_inverse_of_s_is_lapacks_run_eagerly_and_cofactors_traced(m):
    gen = torch.Generator().manual_seed(1)
    S = _spd(8, m, gen)
    cofactors = inverse_sym3(S) if m == 3 else inverse_sym2(S)
    torch.testing.assert_close(inverse_sym(S), cofactors, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(inverse_sym(S) @ S, torch.eye(m, dtype=S.dtype).expand(8, m, m),
                               rtol=0, atol=1e-10)
    graph = str(torch.jit.trace(inverse_sym, S).graph)  # ONNX has no matrix inverse
    assert "linalg_inv" not in graph and "aten::mul" in graph
    assert "linalg_inv" in str(torch.jit.trace(lambda s: torch.linalg.inv_ex(s)[0], S).graph)


def test_every_channel_held_is_the_mask_of_ones_bit_for_bit():
    """``mask=None`` (the window filter's training loop) leaves the mask's products out; they
    multiply by 1 and add 0, so the numbers are the same to the last bit."""
    gen = torch.Generator().manual_seed(2)
    B, n = 32, 5
    P, R = _spd(B, n, gen), _spd(B, 3, gen)
    H = _randn(gen, 3, n)
    z, y = _randn(gen, B, n), _randn(gen, B, 3)
    ones = torch.ones(B, 3, dtype=torch.float64)
    for h in (H, None):
        zz, PP = (z, P) if h is not None else (z[:, :3], P[:, :3, :3])
        a = masked_update(zz, PP, y, R, h)
        b = masked_update(zz, PP, y, R, h, ones)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])

"""The learned filters' measurement update, in torch: one update for the window filter's
window form and its recursive form (:mod:`lbo.models.recursive`), whatever a row holds.

A row holds any subset of the three measured channels ``[x, y, heading]`` (a position fix
with or without a heading; the course over ground standing in for the heading where the row
has no ``psi_m``). :func:`masked_update` is the Kalman update with the held channels alone,
written with fixed shapes (a mask, not a gather) so that it batches over rows that hold
different subsets and exports to TorchScript and ONNX. :func:`step_covariance` is the R of
such a row: the filter's own R, with the receiver's reported accuracies in place of its
variances where the receiver reports one.
"""

from __future__ import annotations

import torch


def inverse_sym3(s: torch.Tensor) -> torch.Tensor:
    """Inverse of symmetric positive-definite (B, 3, 3) matrices by cofactors.

    Written out so that TorchScript and ONNX export it (ONNX has no matrix inverse).
    """
    a, b, c = s[:, 0, 0], s[:, 0, 1], s[:, 0, 2]
    d, e, f = s[:, 1, 1], s[:, 1, 2], s[:, 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    rows = [torch.stack([c00, c01, c02], -1), torch.stack([c01, c11, c12], -1),
            torch.stack([c02, c12, c22], -1)]
    return torch.stack(rows, -2) / det[:, None, None]


def inverse_sym2(s: torch.Tensor) -> torch.Tensor:
    """Inverse of symmetric positive-definite (B, 2, 2) matrices, written out as
    :func:`inverse_sym3` is."""
    a, b, d = s[:, 0, 0], s[:, 0, 1], s[:, 1, 1]
    rows = [torch.stack([d, -b], -1), torch.stack([-b, a], -1)]
    return torch.stack(rows, -2) / (a * d - b * b)[:, None, None]


def mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for batches of small matrices, a (..., n, k) and b (..., k, m) -> (..., n, m).

    Compiled (``torch.compile``, ``torch.export``), as a broadcast product and a sum, which the
    compiler fuses with the operations around it into one loop: a batched matrix product is a
    library call of its own for every pair, and a fifth of a compiled carried training step
    went to those calls (17% faster a step so, ``benchmarks/bench_carried.py``). Eager and
    traced, the one call."""
    if torch.compiler.is_compiling():
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ b


def masked_update(z: torch.Tensor, P: torch.Tensor, y: torch.Tensor, mask: torch.Tensor,
                  R: torch.Tensor, H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Kalman update of states z (B, n) with covariances P (B, n, n) by the innovations
    y (B, m) (headings wrapped) of a measurement ``H z`` (H (m, n), or (B, m, n) per row: a
    linearised model's) with covariance R (B, m, m), using only the channels where mask (B, m)
    is 1; m is 3 (a pose: ``[x, y, heading]``) or 2 (the side-slip filter's ``[ay, r]``).

    The other channels' innovations and gains are zeroed and S gets a 1 on their diagonal, so
    that S stays invertible and the update equals the one with the held channels alone. The
    covariance is updated in Joseph form, ``(I - K H) P (I - K H)^T + K R K^T``: over hours of
    steps, ``(I - K H) P`` loses its symmetry. Returns the updated z (B, n) and P (B, n, n)."""
    m = y.shape[-1]
    eye_m = torch.eye(m, dtype=P.dtype, device=P.device)
    y = y * mask
    Ht = H.transpose(-1, -2)
    PH = mm(P, Ht)
    S = (mm(H, PH) + R) * (mask[:, :, None] * mask[:, None, :]) \
        + (1 - mask)[:, :, None] * eye_m  # diag(1 - mask): ONNX has no diag_embed
    if m == 3:  # written out, as TorchScript scripts it (no function as a value)
        S_inv = inverse_sym3(S)
    else:
        S_inv = inverse_sym2(S)
    return joseph(z, P, mm(PH * mask[:, None, :], S_inv), y, H, R)


def joseph(z: torch.Tensor, P: torch.Tensor, K: torch.Tensor, y: torch.Tensor,
           H: torch.Tensor, R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Kalman update given its gain: states z (B, n), covariances P (B, n, n), gain
    K (B, n, m), innovations y (B, m), H (m, n) or (B, m, n), R (B, m, m). Returns
    ``z + K y`` and Joseph's ``(I - K H) P (I - K H)^T + K R K^T``, symmetrised: every torch
    filter's update, whichever way it solves for the gain (by cofactors where it exports,
    :func:`masked_update`; by Cholesky where it also scores the innovation,
    :mod:`lbo.models.gyro_filter`)."""
    eye = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device)
    I_KH = eye - mm(K, H)
    P = mm(mm(I_KH, P), I_KH.transpose(-1, -2)) + mm(mm(K, R), K.transpose(-1, -2))
    return z + mm(K, y.unsqueeze(-1)).squeeze(-1), 0.5 * (P + P.transpose(-1, -2))


def full_update(z: torch.Tensor, P: torch.Tensor, y: torch.Tensor, R: torch.Tensor,
                eye: torch.Tensor, H: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """The window filter's update with every channel of a pose held: states z (B, n),
    covariances P (B, n, n), innovations y (B, 3), R (B, 3, 3), ``eye`` the (n, n) identity
    (made once per window, outside its loop) and H (3, n), or None where the state is the pose
    (H = I, its products left out). ``K = P H^T (H P H^T + R)^-1``, ``z + K y`` and ``(I - K
    H) P`` symmetrised: the short form, in the hot loop of a window's training; the Joseph form
    (:func:`masked_update`) is for rows that hold some channels, and for filters carried for
    hours."""
    if H is None:
        K = P @ inverse_sym3(P + R)
        P_new = (eye - K) @ P
    else:
        PH = P @ H.T  # (B, n, 3)
        K = PH @ inverse_sym3(H @ PH + R)
        P_new = (eye - K @ H) @ P
    z_new = z + (K @ y.unsqueeze(-1)).squeeze(-1)
    return z_new, 0.5 * (P_new + P_new.transpose(1, 2))


def taken(first: torch.Tensor, fix: torch.Tensor, start: tuple[torch.Tensor, torch.Tensor],
          updated: tuple[torch.Tensor, torch.Tensor], predicted: tuple[torch.Tensor, torch.Tensor]
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """The state ``(z (B, n), P (B, n, n))`` of a step of B filters: ``start`` where it is a
    filter's first fix (``first`` (B,) bool), ``updated`` where it holds a fix it updates with
    (``fix`` (B,) bool), ``predicted`` elsewhere."""
    z = torch.where(first[:, None], start[0],
                    torch.where(fix[:, None], updated[0], predicted[0]))
    P = torch.where(first[:, None, None], start[1],
                    torch.where(fix[:, None, None], updated[1], predicted[1]))
    return z, P


def step_covariance(R: torch.Tensor, sigma: torch.Tensor, told: torch.Tensor,
                    course_var: torch.Tensor, measured: torch.Tensor) -> torch.Tensor:
    """A row's R (..., 3, 3) of ``[x, y, heading]`` (x and y in world axes): the filter's R
    (..., 3, 3), with the variance of each channel the receiver reports an accuracy for
    (``told`` (..., 3) of ``[sx_m, sy_m, spsi_m]``, the 1-sigmas ``sigma`` (..., 3), any value
    where not told) replaced by its square and that channel's correlations dropped, and the
    heading's by ``course_var`` (...,) where ``measured`` (...,) is False (the course over
    ground stands in for a heading the row does not hold)."""
    diag = torch.stack([R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]], -1)  # ONNX: no diagonal
    var = torch.where(told, sigma * sigma, diag)
    heading = torch.where(measured, var[..., 2], course_var)
    xy = torch.where(told[..., 0] | told[..., 1], torch.zeros_like(R[..., 0, 1]), R[..., 0, 1])
    zero = torch.zeros_like(xy)
    return torch.stack([torch.stack([var[..., 0], xy, zero], -1),
                        torch.stack([xy, var[..., 1], zero], -1),
                        torch.stack([zero, zero, heading], -1)], -2)


def turn_xy(R: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Covariances R (..., 3, 3) of ``[x, y, heading]`` with their x and y turned by the angle
    of cosine c and sine s (...,): ``T R T^T``, T the rotation of the plane."""
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    T = torch.stack([torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1),
                     torch.stack([zero, zero, one], -1)], -2)
    return T @ R @ T.transpose(-1, -2)

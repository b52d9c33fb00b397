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


def inverse_sym(s: torch.Tensor) -> torch.Tensor:
    """Inverse of symmetric positive-definite (B, m, m) matrices, m 2 or 3: LAPACK's where
    the step runs as it is written (eager, training or not), by cofactors where it is scripted,
    traced, compiled or exported (:func:`inverse_sym3`, :func:`inverse_sym2`). The written-out
    inverse and its gradient take some forty small operations, LAPACK's a few: a window
    filter's training loop inverts an S at every row, and this saves more there than Joseph's
    form costs (``benchmarks/bench_update.py``)."""
    if not torch.jit.is_scripting():  # TorchScript compiles only the other branch
        if not (torch.jit.is_tracing() or torch.compiler.is_compiling()
                or torch.onnx.is_in_onnx_export()):
            return torch.linalg.inv_ex(s)[0]
    if s.shape[-1] == 3:  # written out, as TorchScript scripts it (no function as a value)
        return inverse_sym3(s)
    return inverse_sym2(s)


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


def masked_update(z: torch.Tensor, P: torch.Tensor, y: torch.Tensor, R: torch.Tensor,
                  H: torch.Tensor | None = None, mask: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The Kalman update of states z (B, n) with covariances P (B, n, n) by the innovations
    y (B, m) (headings wrapped) of a measurement ``H z`` (H (m, n), or (B, m, n) per row: a
    linearised model's; None where the state is what is measured, H = I, whose products are
    left out) with covariance R (B, m, m), using only the channels where mask (B, m) is 1
    (None: every channel); m is 3 (a pose: ``[x, y, heading]``) or 2 (the side-slip filter's
    ``[ay, r]``). S is inverted by :func:`inverse_sym`, the covariance updated by
    :func:`joseph`.

    The other channels' innovations and gains are zeroed and S gets a 1 on their diagonal, so
    that S stays invertible and the update equals the one with the held channels alone.
    Returns the updated z (B, n) and P (B, n, n)."""
    m = y.shape[-1]
    PHt = P if H is None else mm(P, H.transpose(-1, -2))  # (B, n, m)
    S = (P if H is None else mm(H, PHt)) + R
    if mask is None:
        gain_rows = PHt
    else:
        eye_m = torch.eye(m, dtype=P.dtype, device=P.device)
        y = y * mask
        S = S * (mask[:, :, None] * mask[:, None, :]) \
            + (1 - mask)[:, :, None] * eye_m  # diag(1 - mask): ONNX has no diag_embed
        gain_rows = PHt * mask[:, None, :]
    return joseph(z, P, PHt, mm(gain_rows, inverse_sym(S)), y, R, H)


def joseph(z: torch.Tensor, P: torch.Tensor, PHt: torch.Tensor, K: torch.Tensor,
           y: torch.Tensor, R: torch.Tensor, H: torch.Tensor | None = None
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """The Kalman update given its gain, every torch filter's, whichever way it solves for the
    gain (:func:`masked_update`'s, S inverted by :func:`inverse_sym`; by Cholesky where it
    also scores the innovation, :mod:`lbo.models.gyro_filter`): states z (B, n), covariances
    P (B, n, n), ``P H^T`` (B, n, m) (the gain's), gain K (B, n, m), innovations y (B, m),
    R (B, m, m), and H (m, n) or (B, m, n), or None for H = I.

    Returns ``z + K y`` and Joseph's covariance ``(I - K H) P (I - K H)^T + K R K^T``,
    symmetrised: over hours of steps the short form ``(I - K H) P`` loses its symmetry and,
    where R is small against P, its positive definiteness. Joseph's form is computed
    factored, ``A P - (A P H^T - K R) K^T`` with ``A P = P - K (P H^T)^T`` (P is symmetric):
    the same polynomial in K, expanded (so an error in the gain still costs only its square),
    in one batched product fewer (two where H = I), which the window filter's training loop
    pays at every row."""
    AP = P - mm(K, PHt.transpose(-1, -2))
    APHt = AP if H is None else mm(AP, H.transpose(-1, -2))
    P = AP - mm(APHt - mm(K, R), K.transpose(-1, -2))
    return z + mm(K, y.unsqueeze(-1)).squeeze(-1), 0.5 * (P + P.transpose(-1, -2))


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

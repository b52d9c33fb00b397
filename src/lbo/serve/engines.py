"""Inference engines of a learned observer: TorchScript and ONNX Runtime next to PyTorch.

Both :mod:`lbo.serve.observer` (``engine=``: :func:`make_predictor` for a window,
:func:`make_recursive_step` for the recursive form) and :mod:`lbo.export` (the files) build on
these, so neither imports the other's internals.
"""

from __future__ import annotations

import contextlib
import io
import math
import re
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from lbo.core.errors import LboError
from lbo.logs.checks import check_device
from lbo.serve import onnx_cache

ENGINES = ("torch", "torchscript", "onnx", "auto")
"""Inference engines for learned observers; ``auto``: ``onnx`` where the recursive form is
kept as ONNX graphs (:mod:`lbo.serve.exported`), else ``torch``."""
OPSET = 20
"""The ONNX opset of the exported files."""
TOLERANCE = 1e-5
"""Largest difference to PyTorch that an exported file may show (tested)."""


def _example(net: Any, batch: int = 1, seed: int = 0):
    """Plausible raw windows (B, N, 5) float64: a vehicle near (100 m, -50 m), noisy. For a
    net that reads a receiver, its windows (B, N, 11): a fix every fifth step, a heading in
    the first half of the batch only, the accuracies, a course and a gyro at every step."""
    import torch

    g = torch.Generator().manual_seed(seed)
    win = torch.randn(batch, net.window, 5, generator=g, dtype=torch.float64)
    win = win * torch.tensor([1.0, 1.0, 0.02, 2.0, 0.05], dtype=torch.float64) + torch.tensor(
        [100.0, -50.0, 0.5, 10.0, 0.0], dtype=torch.float64)
    if not getattr(net, "receiver", False):
        return win
    from lbo.models.receiver_window import COLUMNS, widen

    c, b, n, f64 = {name: i for i, name in enumerate(COLUMNS)}, batch, net.window, torch.float64
    rx = widen(win)
    rx[:, :, c["sx_m"]:c["sy_m"] + 1] = 0.5 + torch.rand(b, n, 2, generator=g, dtype=f64)
    rx[:, :, c["course"]] = win[:, :, 2] + 0.05 * torch.randn(b, n, generator=g, dtype=f64)
    rx[:, :, c["s_course"]] = 0.05
    rx[:, :, c["r_m"]] = 0.02 * torch.randn(b, n, generator=g, dtype=f64)
    rx[:, torch.arange(n) % 5 != 0, :c["s_course"] + 1] = float("nan")  # a fix every fifth
    rx[b // 2:, :, c["psi_m"]] = float("nan")
    rx[:, :, c["spsi_m"]] = torch.where(rx[:, :, c["psi_m"]].isfinite(), 0.01, float("nan"))
    return rx


def _without_fixes(win):
    """A copy of the windows (B, N, 5) with every other fix dropped, and, in the second half
    of the batch, none in the first quarter of the window either (NaN measurements)."""

    win = win.clone()
    win[:, 1::2, :3] = float("nan")
    win[len(win) // 2:, : max(1, win.shape[1] // 4), :3] = float("nan")
    return win


def exporting(form: str, net: Any, make: Callable[[], Any]) -> Any:
    """``make()``, a failure said in one line: a plug-in's model may use what TorchScript or
    ONNX cannot hold (an operator without an ONNX form, Python on the tensors' values)."""
    try:
        return make()
    except Exception as e:
        while e.__cause__ is not None:  # the dynamo exporter's first line is generic
            e = e.__cause__  # type: ignore[assignment]
        reason = re.sub(r"\x1b\[[0-9;]*m", "", (str(e).strip().splitlines() or [""])[0])[:200]
        raise LboError(f"engine: model {type(net.net).__name__} does not export to {form} "
                       f"({type(e).__name__}: {reason}); it still runs with engine=torch"
                       ) from None


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Silence what torch's exporters say that is no concern of a user's: jit.trace's and the
    TorchScript-based ONNX exporter's deprecation, nn.LSTM's shape checks while traced, and
    the dynamo exporter's notes (torchvision's operators, its own FutureWarnings, attributes
    set in a forward, the batch axis's name, its optimiser's line per merged initializer)."""
    import logging

    from torch.jit import TracerWarning

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.")
        warnings.filterwarnings("ignore", message=r"You are using the legacy TorchScript-based "
                                r"ONNX export")  # warned at the caller's line
        warnings.filterwarnings("ignore", category=TracerWarning)
        warnings.filterwarnings("ignore", message=r".*nn\.LSTM|.*RNN module weights",
                                category=UserWarning)
        warnings.filterwarnings("ignore", message=r".*LeafSpec|_check_is_size",
                                category=FutureWarning)
        # nn.LSTM's weights and the recursive step's record for the smoother, set as a
        # forward runs; and the dynamic axes, one name for the batch of every input
        warnings.filterwarnings("ignore", message=r"The tensor attributes .* were assigned "
                                r"during export|# The axis name: batch", category=UserWarning)
        loggers = [logging.getLogger(name) for name in ("torch.onnx", "onnxscript", "onnx_ir")]
        levels = [lg.level for lg in loggers]
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        try:
            yield
        finally:
            for lg, level in zip(loggers, levels):
                lg.setLevel(level)


def trace(net: Any) -> Any:
    """TorchScript of an :class:`~lbo.models.net.WindowNet`, traced on one float64 window
    on the net's device.

    Traced rather than scripted: the feature functions branch on Python types. The trace
    holds for any batch size (checked in the tests). Still torch.jit: ``torch.export``'s
    program, the successor, ran the robust observer's window 2 times slower than eager
    PyTorch (26 against 13 ms, N = 40, one thread, measured once), where the trace runs faster.
    """
    import torch

    net = net.eval()
    example = _example(net).to(net.in_mean.device)
    with _quiet():
        return exporting("TorchScript", net,
                          lambda: torch.jit.trace(net, example, check_trace=False))


def dynamo_onnx(module: Any, args: tuple, names: tuple[list[str], list[str]],
                 dynamic: Any) -> bytes:
    """ONNX (opset :data:`OPSET`) of ``module`` by the dynamo exporter (``torch.export``,
    then onnxscript's translation and optimiser), its batch axis dynamic (``dynamic``: the
    ``dynamic_shapes`` of the example ``args``, whose batch must not be 1)."""
    import torch

    with _quiet():
        program = torch.onnx.export(module, args, dynamo=True, opset_version=OPSET,
                                    input_names=names[0], output_names=names[1],
                                    dynamic_shapes=dynamic, verbose=False)
    assert program is not None  # given no file, the exporter returns the program
    return program.model_proto.SerializeToString()


def onnx_bytes(net: Any) -> bytes:
    """ONNX model of an :class:`~lbo.models.net.WindowNet`: input ``window`` (batch, N, 5),
    output ``state`` (batch, 3), both float64.

    By the dynamo exporter, but for a window form that runs a filter over its window (the
    window filter, KalmanNet's peers: :func:`lbo.models.carried.can_carry`): the dynamo
    exporter unrolls its N steps into a graph it translates and optimises node by node, and
    took 412 s for the robust observer's window (N = 40; 77 s for KalmanNet at N = 20), where
    the TorchScript-based exporter takes 5.5 s (2.6 s) for the same numbers. Their recursive
    step exports by dynamo (:func:`recursive_onnx_bytes`)."""
    import torch

    from lbo.models.carried import can_carry

    net = net.eval()
    if not can_carry(net.net):
        batch = torch.export.Dim("batch", min=1)
        return exporting("ONNX", net, lambda: dynamo_onnx(
            net, (_example(net, batch=2),), (["window"], ["state"]), ({0: batch},)))
    return exporting("ONNX", net, lambda: legacy_onnx(
        net, (_example(net),), (["window"], ["state"])))


def legacy_onnx(module: Any, args: tuple, names: tuple[list[str], list[str]]) -> bytes:
    """ONNX (opset :data:`OPSET`) of ``module`` by the TorchScript-based exporter, traced on
    the example ``args``, the batch axis of every input and output (``names``) dynamic but
    the step count ``k``'s."""
    import torch

    buf = io.BytesIO()
    axes = {n: {0: "batch"} for n in (*names[0], *names[1]) if n not in ("k", "next_k")}
    with _quiet():
        torch.onnx.export(module, args,
                          buf,  # type: ignore[arg-type]  # torch's stub: it takes a file too
                          dynamo=False, opset_version=OPSET, input_names=names[0],
                          output_names=names[1], dynamic_axes=axes)
    return buf.getvalue()


def onnx_session(model: bytes | str | Path, threads: int | None = None) -> Any:
    """An ONNX Runtime CPU session; ``threads`` intra-op threads (None: its default)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads is not None:
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"])


def kept_export(module: Any, form: str, export: Callable[[], bytes]) -> tuple[bytes, Any]:
    """``module``'s ONNX export as ``form`` and a one-thread session of it, the export kept
    between sessions (:func:`lbo.serve.onnx_cache.kept`)."""
    return onnx_cache.kept(module, form, OPSET, export,
                           lambda model: onnx_session(model, threads=1))


def check_exported(net: Any, script: Any, session: Any, batch: int = 64) -> dict[str, float]:
    """Largest |difference| of TorchScript and ONNX Runtime to PyTorch on random windows
    (and the same with fixes missing, for a net that takes them)."""
    import torch

    win = _example(net, batch=batch, seed=1)
    if getattr(net, "fixes", False):
        win = torch.cat([win, _without_fixes(win)])
    with torch.inference_mode():
        ref = net(win).numpy()
        ts = script(win).numpy()
    ort_out = session.run(None, {"window": win.numpy()})[0]
    return {"torchscript": float(np.abs(ts - ref).max()),
            "onnx": float(np.abs(ort_out - ref).max())}


def recursive_example(rec: Any, batch: int = 1) -> tuple:
    """One step's inputs of a :class:`~lbo.models.recursive.RecursiveFilter` for ``batch``
    filters: a fix as a receiver's row (B, 8) (:data:`lbo.filters.measure.CHANNELS`, no
    accuracy nor course), an input (B, I) of its
    :attr:`~lbo.models.recursive.RecursiveFilter.inputs`, and the state of filters that have
    seen nothing."""
    import torch

    from lbo.filters.measure import widen

    f = dict(dtype=torch.float64, device=next(rec.parameters()).device)
    u = [10.0, 0.02, 0.007][:len(rec.inputs)]
    return (torch.tensor(widen([[100.0, -50.0, 0.5]] * batch), **f),
            torch.tensor([u] * batch, **f), *rec.initial_state(batch, f["device"]))


def trace_recursive(rec: Any) -> Any:
    """TorchScript of a recursive filter's step ``(m, u, *state) -> (pose, cov, *state)``,
    traced on one step (the step has no data-dependent Python branch); m is a receiver's row
    (B, 8), :data:`lbo.filters.measure.CHANNELS` (a paper row: NaN beyond ``psi_m``)."""
    import torch

    with _quiet():
        return torch.jit.trace(rec.eval(), recursive_example(rec), check_trace=False)


def recursive_onnx_bytes(rec: Any) -> bytes:
    """ONNX model of a recursive filter's step, by the dynamo exporter: inputs ``m`` (B, 8) (a
    receiver's row, :data:`lbo.filters.measure.CHANNELS`; a paper row: NaN beyond ``psi_m``),
    ``u`` (B, I) and the state tensors named as :data:`~lbo.models.recursive.STATE_NAMES`,
    outputs ``pose`` (B, 3), ``cov`` (B, 3, 3) and ``next_<name>`` for each state tensor, all
    float64. A state tensor the model never reads may not be an input."""
    import torch

    from lbo.models.recursive import STATE_NAMES

    rec = rec.cpu().eval()
    batch = torch.export.Dim("batch", min=1)
    dynamic = {"m": {0: batch}, "u": {0: batch},
               "state": tuple(None if name == "k" else {0: batch} for name in STATE_NAMES)}
    names = (["m", "u", *STATE_NAMES],
             ["pose", "cov", *(f"next_{n}" for n in STATE_NAMES)])
    return exporting("ONNX", rec, lambda: dynamo_onnx(
        rec, recursive_example(rec, batch=2), names, dynamic))


def onnx_step(session: Any, state_names: tuple[str, ...] | None = None) -> Any:
    """The step ``(m, u, state) -> (pose, cov, next state)`` of a recursive filter's ONNX
    session (:func:`recursive_onnx_bytes`), on numpy arrays; m (B, 3) or (B, 8) (widened
    with NaN); ``state`` is every tensor of ``state_names`` (None:
    :data:`~lbo.models.recursive.STATE_NAMES`, which loads torch), of which it feeds those
    the model reads."""
    from lbo.filters.measure import widen

    if state_names is None:
        from lbo.models.recursive import STATE_NAMES

        state_names = STATE_NAMES

    names = [i.name for i in session.get_inputs()]
    keys = ["m", "u", *state_names]

    def step(m: np.ndarray, u: np.ndarray, state: list) -> tuple:
        feed = dict(zip(keys, [widen(m), u, *state]))
        out = session.run(None, {k: feed[k] for k in names})
        return out[0], out[1], out[2:]

    return step


def check_recursive(rec: Any, script: Any, session: Any, steps: int = 300,
                    seed: int = 1) -> dict[str, float]:
    """Largest |difference| of a recursive filter's TorchScript and ONNX step to PyTorch's, in
    pose and covariance, over ``steps`` steps of a noisy drive near (100 m, -50 m). For a
    filter that takes missing fixes, every other fix is missing, and the second half is a
    single antenna's: no ``psi_m``, the fixes' reported accuracy and a course over ground; a
    gyro filter's gyro reads the turn, biased, from the first step."""
    import torch

    from lbo.filters.measure import widen

    rng = np.random.default_rng(seed)
    k = np.arange(steps)
    m = np.stack([100 + 0.2 * k, -50 + 0.01 * k, np.full(steps, 0.05)], 1)
    m = widen(m + rng.normal(size=(steps, 3)) * [1.0, 1.0, 0.02])
    if rec.fixes:
        half = k >= steps // 2
        m[half, 2] = np.nan
        m[half, 3:5] = rng.uniform(0.5, 2.0, size=(int(half.sum()), 1))
        m[half, 6] = 0.05 + 0.03 * rng.standard_normal(int(half.sum()))
        m[half, 7] = 0.03
        m[1::2] = np.nan
    u = np.tile([10.0, 0.01, 10.0 * math.tan(0.01) / 2.7 + 0.004], (steps, 1))
    u = u[:, :len(rec.inputs)]
    step = onnx_step(session)
    worst = {"torchscript": 0.0, "onnx": 0.0}
    states = {e: list(rec.initial_state(1)) for e in ("torch", "torchscript")}
    onnx_state = [s.numpy() for s in rec.initial_state(1)]
    with torch.inference_mode():
        for i in range(steps):
            mk, uk = torch.from_numpy(m[i:i + 1]), torch.from_numpy(u[i:i + 1])
            ref = rec(mk, uk, *states["torch"])
            ts = script(mk, uk, *states["torchscript"])
            states["torch"], states["torchscript"] = list(ref[2:]), list(ts[2:])
            *ox, onnx_state = step(m[i:i + 1], u[i:i + 1], onnx_state)
            for engine, out in (("torchscript", [t.numpy() for t in ts[:2]]), ("onnx", ox)):
                for a, b in zip(out, (ref[0].numpy(), ref[1].numpy())):
                    d = np.abs(a - b)
                    nan_same = np.isnan(a) == np.isnan(b)
                    gap = float(np.nanmax(d)) if np.isfinite(d).any() else 0.0
                    worst[engine] = max(worst[engine], gap if nan_same.all() else float("nan"))
    return worst


# --------------------------------------------------------------------------- in an observer


def engine_device(engine: str, device: Any) -> Any:
    """The checked device of ``engine``: one of :data:`ENGINES`, and ONNX on the CPU only."""
    if engine not in ENGINES:
        raise LboError(f"engine must be one of {list(ENGINES)}, got {engine!r}")
    device = check_device(device)
    if engine == "onnx" and str(device) != "cpu":
        raise LboError(f"engine=onnx runs on the CPU (ONNX Runtime's CPU provider), "
                       f"got device={device}")
    return device


Predictor = Callable[[np.ndarray], np.ndarray]
"""Windows (B, N, 5) float64 ``[x_m, y_m, psi_m, V, delta]`` -> states (B, 3) float64."""


def make_predictor(net: Any, engine: str = "torch", device: str = "cpu") -> Predictor:
    """Wrap an :class:`~lbo.models.net.WindowNet` as a numpy-in, numpy-out predictor.

    ``torchscript`` traces the net; ``onnx`` exports it (or reads the export kept from an
    earlier session, :mod:`lbo.serve.onnx_cache`) and runs it in ONNX Runtime on one thread
    (one window per step gains nothing from more). The torch engines use torch's threads: in
    a control loop call ``torch.set_num_threads(1)``, as intra-op threads slow a single window
    down, by 10x on a busy 2-core machine (measured).
    """
    import torch

    device = engine_device(engine, device)
    net = net.to(device).eval()
    if engine == "onnx":
        net = net.cpu()
        session = kept_export(net, "window", lambda: onnx_bytes(net))[1]
        return lambda win: session.run(None, {"window": win})[0]
    if engine == "torchscript":
        net = trace(net)

    def predict(win: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return net(torch.from_numpy(win).to(device)).cpu().numpy()

    return predict


RecursiveStep = Callable[[np.ndarray, np.ndarray, list], tuple[np.ndarray, np.ndarray, list]]
"""The recursive form's step: measurement (1, 3) or a receiver's row (1, 8)
(:data:`lbo.filters.measure.CHANNELS`), input (1, 2), state -> pose (1, 3), covariance
(1, 3, 3), new state (float64 numpy arrays in, out)."""


Coast = Callable[[np.ndarray, list], tuple[np.ndarray, np.ndarray, list]]
"""Rows without any measurement at once: their inputs (K, 2), state -> poses (K, 3),
covariances (K, 3, 3), new state (:meth:`~lbo.models.recursive.RecursiveFilter.coast`)."""


def chunked(coast: Coast, limit: int) -> Coast:
    """``coast`` (which takes 1 to ``limit`` rows a call: its ring slots, each written once)
    over any number of rows, ``limit`` at a time."""
    def over(u: np.ndarray, st: list) -> tuple[np.ndarray, np.ndarray, list]:
        poses, covs = [], []
        for a in range(0, len(u), limit):
            pose, cov, st = coast(u[a:a + limit], st)
            poses.append(pose)
            covs.append(cov)
        return np.concatenate(poses), np.concatenate(covs), st

    return over


def make_recursive_step(net: Any, engine: str = "torch", device: str = "cpu"
                        ) -> tuple[RecursiveStep, list, Coast | None]:
    """The recursive form (:class:`~lbo.models.recursive.RecursiveFilter`) of a window filter
    ``net`` (an :class:`~lbo.models.net.WindowNet` of ``filternet``) as a numpy step function on
    ``engine``, its initial state, and, where the filter :attr:`coasts`, its coast over rows
    without a measurement (in PyTorch, on the state of any engine; else None). ``onnx`` runs
    on one thread, as in a control loop."""
    import torch

    from lbo.filters.measure import widen
    from lbo.models.recursive import RecursiveFilter

    device = engine_device(engine, device)
    rec = RecursiveFilter(net.net.cpu() if engine == "onnx" else net.net).to(device)
    state = [s.cpu().numpy() for s in rec.initial_state(1)]
    on_cpu = str(device) == "cpu"

    def tensors(*arrays: np.ndarray) -> list:
        # a read-only frame's rows are copied; on the CPU the tensors share the arrays'
        # memory (a step's tenth, were each moved)
        out = [torch.from_numpy(x if x.flags.writeable else x.copy()) for x in arrays]
        return out if on_cpu else [x.to(device) for x in out]

    def coast(u: np.ndarray, st: list) -> tuple:
        with torch.inference_mode():
            pose, cov, *st = (x.cpu().numpy() for x in rec.coast(*tensors(u, *st)))
        return pose, cov, st

    coaster = chunked(coast, rec.coast_limit) if rec.coasts else None
    if engine == "onnx":
        kept = kept_export(rec, "recursive", lambda: recursive_onnx_bytes(rec))[1]
        return onnx_step(kept), state, coaster
    module = rec
    if engine == "torchscript":
        module = trace_recursive(rec)

    def torch_step(m: np.ndarray, u: np.ndarray, st: list) -> tuple:
        with torch.inference_mode():
            out = [o.cpu().numpy() for o in module(*tensors(widen(m), u, *st))]
        return out[0], out[1], out[2:]

    return torch_step, state, coaster

"""ONNX export by torch's two exporters: how long each takes, and how fast its file runs.

    python benchmarks/bench_export.py [--models cnn lstm kalmannet filternet step]
                                      [--window 20] [--repeats 200]

lbo exports by the dynamo exporter (``torch.onnx.export(dynamo=True)``: ``torch.export``,
then onnxscript's translation and optimiser), but a window form that runs a filter over its
window: that loop is unrolled into N steps of graph, which the dynamo exporter translates and
optimises node by node. For each model (untrained, the batch axis dynamic, one thread), this
prints each exporter's export time, the largest difference of its file to PyTorch on 8
windows, and the median ms of one window (one step) in ONNX Runtime:

- ``cnn``, ``lstm``: the paper's nets; ``kalmannet``: KalmanNet's window form;
- ``filternet``: the robust observer's window form (kinematic bicycle, the fix channel);
- ``step``: the robust observer's recursive step (one sample in), its streaming form.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

MODELS = {"cnn": {}, "lstm": {}, "kalmannet": {"features": "frame"},
          "filternet": {"features": "frame", "fixes": True},
          "step": {"features": "frame", "fixes": True}}


def case(model: str, window: int, repeats: int) -> None:
    """Print both exporters' figures for ``model``."""
    from lbo.models.net import WindowNet
    from lbo.models.recursive import STATE_NAMES, RecursiveFilter
    from lbo.serve import engines

    torch.manual_seed(0)
    net = WindowNet("filternet" if model == "step" else model, window, **MODELS[model]).eval()
    if model == "step":
        module: torch.nn.Module = RecursiveFilter(net.net).eval()
        args = engines.recursive_example(module)
        names = (["m", "u", *STATE_NAMES], ["pose", "cov", *(f"next_{n}" for n in STATE_NAMES)])
        dynamo = lambda: engines.recursive_onnx_bytes(module)  # noqa: E731
    else:
        module, args = net, (engines._example(net),)
        names = (["window"], ["state"])
        batch = torch.export.Dim("batch", min=1)
        dynamo = lambda: engines.dynamo_onnx(  # noqa: E731
            net, (engines._example(net, batch=2),), names, ({0: batch},))
    for exporter, make in (("legacy", lambda: engines.legacy_onnx(module, args, names)),
                           ("dynamo", dynamo)):
        start = time.perf_counter()
        model_bytes = make()
        took = time.perf_counter() - start
        session = engines.onnx_session(model_bytes, threads=1)
        wanted = {i.name for i in session.get_inputs()}
        if model == "step":
            feed = dict(zip(names[0], [a.numpy() for a in args]))
            with torch.inference_mode():
                ref = module(*args)[0].numpy()
            diff = float(np.abs(session.run(None, {k: feed[k] for k in wanted})[0] - ref).max())
        else:
            win = engines._example(net, batch=8, seed=1)
            with torch.inference_mode():
                ref = net(win).numpy()
            diff = float(np.abs(session.run(None, {"window": win.numpy()})[0] - ref).max())
            feed = {"window": win[:1].numpy()}
        feed = {k: feed[k] for k in wanted}
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            session.run(None, feed)
            times.append(time.perf_counter() - start)
        print(f"{model:>10} {exporter:>7} {took:>9.1f} {diff:>9.1e} "
              f"{1e3 * statistics.median(times):>9.3f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--window", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"ONNX export, N = {args.window} ({torch.__version__}, CPU, one thread)")
    print(f"{'model':>10} {'exporter':>7} {'export s':>9} {'max diff':>9} {'ms/call':>9}")
    for model in args.models:
        case(model, args.window, args.repeats)


if __name__ == "__main__":
    main()

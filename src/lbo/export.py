"""`python -m lbo.export`: a trained observer as TorchScript and ONNX files, for a control loop.

    python -m lbo.export observer=<checkpoint | run id | models:/name/version> out_dir=exports
    python -m lbo.export observer=<run id> register=lbo-cnn     # also: models:/lbo-cnn/<version>
    python -m lbo.export observer=<run id> register=lbo-cnn alias=champion  # and @champion

Writes ``<name>.pt`` (TorchScript, traced), ``<name>.onnx`` (opset 20, dynamic batch axis) and
``<name>.json`` (window, dt, features, channel order, vehicle, noise). A CNN's or LSTM's files
(and a window filter's with ``form=window``) take the raw window (B, N, 5) float64 ``[x_m,
y_m, psi_m, V, delta]``, oldest sample first, and return (B, 3) float64 ``[x, y, psi]`` at the
window's last step: the feature transform and the normalisation are inside. The robust
observer's files are its recursive form's step (:mod:`lbo.models.recursive`): one sample
``m`` (B, 8) (a receiver's row, :data:`lbo.filters.measure.CHANNELS`: the fix, its reported
accuracy, the course over ground; NaN where not held) and ``u`` (B, 2) and the filter's state
in, the pose (B, 3), its covariance
(B, 3, 3) and the next state out; the JSON lists the state tensors, their shapes and their
start (all zeros). Each file is checked against PyTorch (random windows; 300 steps of a drive
with missing fixes) before it is kept.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from lbo.core.atomic import atomic_path, remove_stale_temps
from lbo.core.cli import entry
from lbo.core.errors import LboError
from lbo.serve.engines import (
    OPSET,
    TOLERANCE,
    check_exported,
    check_recursive,
    kept_export,
    onnx_bytes,
    recursive_onnx_bytes,
    trace,
    trace_recursive,
)
from lbo.serve.runners import is_window_filter


def export(observer: Any, out_dir: str | Path, name: str | None = None) -> dict[str, Path]:
    """Write ``<name>.pt``, ``<name>.onnx`` and ``<name>.json`` of a learned observer, in the
    form it runs in (``observer.form``: a window function, or the recursive form's step).

    Parameters
    ----------
    observer : a learned :class:`~lbo.serve.observer.Observer`.
    out_dir : folder to write to (created).
    name : file stem (:func:`check_name`: no folder); default the observer's name (``cnn-N60``).

    Returns
    -------
    ``{"torchscript": path, "onnx": path, "json": path}``.

    Raises
    ------
    LboError
        For a classical observer, or an export that differs from PyTorch by more than
        :data:`TOLERANCE`.
    """
    import torch

    name = check_name(name)
    if observer.net is None:
        raise LboError(f"export needs a learned observer (a checkpoint, run id or models:/ "
                       f"URI), not the classical {observer.name!r}")
    net = copy.deepcopy(observer.net).cpu().eval()  # the observer keeps its device
    bad = [k for k, v in net.state_dict().items()
           if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise LboError(f"export: {observer.name}'s weights hold NaN or inf ({bad[0]}; a "
                       "diverged training?); nothing written")
    name = name or observer.name
    out = Path(out_dir)
    if observer.form == "recursive" and not is_window_filter(net):
        raise LboError(f"export: {observer.name} runs carried from step to step, and only the "
                       "window filter's carried step is exported; export its window form "
                       "with form=window; nothing written")
    if observer.form == "recursive":
        from lbo.models.recursive import RecursiveFilter

        rec = RecursiveFilter(net.net)
        model, session = kept_export(rec, "recursive", lambda: recursive_onnx_bytes(rec))
        script = trace_recursive(rec)
        diff = check_recursive(rec, script, session)
    else:
        model, session = kept_export(net, "window", lambda: onnx_bytes(net))
        script = trace(net)
        diff = check_exported(net, script, session)
    worst = max(diff, key=lambda k: diff[k] if diff[k] == diff[k] else float("inf"))  # NaN
    if not diff[worst] <= TOLERANCE:  # NaN fails too
        raise LboError(f"export: {worst} differs from PyTorch by {diff[worst]:.2e} "
                       f"(> {TOLERANCE:g}, or not finite); nothing written")
    paths = {"torchscript": out / f"{name}.pt", "onnx": out / f"{name}.onnx",
             "json": out / f"{name}.json"}
    with _export_lock(out):
        # under the lock, the temps of these three files are a killed export's; any other
        # hidden file in the folder may be another program's, and stays
        removed = remove_stale_temps(out, [p.name for p in paths.values()])
        if removed:
            print(f"removed {len(removed)} temp file(s) of an export killed before it finished "
                  f"from {out}")
        sidecar = _sidecar(observer, net, name, diff, paths)
        if observer.form == "recursive":
            sidecar.update(_step_sidecar(rec, model))
        _write_set(paths, script, model, sidecar)
    return paths


def check_name(name: Any) -> str | None:
    """``name``, checked: a plain file stem (letters, digits, ``_``, ``.``, ``+``, ``-``; no
    folder), so that the files land in ``out_dir`` and nowhere else. None stays None."""
    if name is None:
        return None
    stem = str(name)
    if not re.fullmatch(r"\w[\w.+-]*", stem):
        raise LboError(f"name must be a plain file stem (letters, digits, _ . + -, starting "
                       f"with a letter or digit; no folder: give that as out_dir=), got {stem!r}")
    return stem


def _write_set(paths: dict[str, Path], script: Any, model: bytes,
               sidecar: dict[str, Any]) -> None:
    """Write the three files as one set: each to a temp file first, then all renamed into
    place, the sidecar last, and only once all three are written (a failure replaces none).
    The sidecar records the sha256 of the other two."""
    import hashlib

    import torch

    with atomic_path(paths["json"]) as tmp_json, atomic_path(paths["onnx"]) as tmp_onnx, \
            atomic_path(paths["torchscript"]) as tmp_pt:
        torch.jit.save(script, str(tmp_pt))
        tmp_onnx.write_bytes(model)
        sidecar["sha256"] = {paths[k].name: hashlib.sha256(p.read_bytes()).hexdigest()
                             for k, p in (("torchscript", tmp_pt), ("onnx", tmp_onnx))}
        tmp_json.write_text(json.dumps(sidecar, indent=2, allow_nan=False) + "\n")


@contextlib.contextmanager
def _export_lock(out: Path) -> Iterator[None]:
    """Exports into one folder take turns: an exclusive flock on the folder itself, so the
    folder holds nothing but exports and no lock file is left anywhere."""
    import fcntl
    import os

    try:
        out.mkdir(parents=True, exist_ok=True)
        fd = os.open(out, os.O_RDONLY)
    except OSError as e:
        raise LboError(f"cannot write {out}: {e.strerror or e}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing drops the lock


def _step_sidecar(rec: Any, model: bytes) -> dict[str, Any]:
    """What a control loop needs to call the recursive form's step: its inputs and outputs,
    and the state it starts from."""
    from lbo.filters.measure import CHANNELS
    from lbo.models.recursive import STATE_NAMES
    from lbo.serve.engines import onnx_session

    state = rec.initial_state(1)
    used = {i.name for i in onnx_session(model).get_inputs()}
    return {
        "form": "recursive",
        "input": {"m": {"shape": ["batch", len(CHANNELS)], "columns": list(CHANNELS),
                        "units": ["m", "m", "rad", "m", "m", "rad", "rad", "rad"],
                        "not_held": "NaN: a paper fix is x_m, y_m, psi_m and five NaN; a "
                                    "position fix without a heading has psi_m NaN; sx_m, sy_m, "
                                    "spsi_m NaN: the noise model's R; course NaN: no course "
                                    "over ground (lbo.filters.measure.course_over_ground)",
                        "missing_fix": "every channel NaN" if rec.fixes else
                        "not allowed: a full fix at every step, the other channels NaN"},
                  "u": {"shape": ["batch", len(rec.inputs)], "columns": list(rec.inputs),
                        **({"r_m": "the gyro's last reading (rad/s), NaN before the first"}
                           if rec.gyro else {})},
                  "dtype": "float64",
                  "state": "the state tensors below, as the last call returned them"},
        "output": {"pose": {"shape": ["batch", 3], "columns": ["x", "y", "psi"],
                            "units": ["m", "m", "rad"], "before_first_fix": "NaN"},
                   "cov": {"shape": ["batch", 3, 3], "units": "m^2, m rad, rad^2"},
                   "next state": "next_<name> for each state tensor"},
        "state": [{"name": n, "shape": ["batch", *list(t.shape[1:])] if n != "k" else [1],
                   "start": 0.0, "onnx_input": n in used}
                  for n, t in zip(STATE_NAMES, state)],
        "call": "start with every state tensor zero; each step: feed m, u and the state, keep "
                "pose and cov, pass next_<name> back as <name> (ONNX: only the tensors with "
                "onnx_input true are inputs)",
    }


def _sidecar(observer: Any, net: Any, name: str, diff: dict[str, float],
             paths: dict[str, Path]) -> dict[str, Any]:
    from lbo.models.receiver_window import COLUMNS
    from lbo.sim.columns import WINDOW

    columns = list(COLUMNS if getattr(net, "receiver", False) else WINDOW)
    return {
        "name": name,
        "model": type(net.net).__name__,
        "window": observer.window,
        "dt": observer.dt,
        "features": observer.features,
        "input": {"name": "window", "shape": ["batch", observer.window, len(columns)],
                  "dtype": "float64", "columns": columns,
                  "order": "oldest sample first; the last row is the current step",
                  "missing_fix": ("x_m, y_m and psi_m NaN" if getattr(net, "fixes", False)
                                  else "not allowed: a fix at every step")},
        "output": {"name": "state", "shape": ["batch", 3], "dtype": "float64",
                   "columns": ["x", "y", "psi"], "units": ["m", "m", "rad"]},
        "vehicle": dataclasses.asdict(observer.vehicle),
        "noise": {"name": observer.noise.name,
                  "process_sigma": list(observer.noise.process_sigma),
                  "measurement_sigma": list(observer.noise.measurement_sigma)},
        "onnx_opset": OPSET,
        "max_abs_diff_to_pytorch": diff,
        "source": observer.meta.get("source"),
        "data_hash": observer.meta.get("data_hash"),
        # the range of inputs it was trained on (lbo.models.envelope), for the loop to check
        "envelope": observer.envelope.to_dict() if observer.envelope is not None else None,
        "files": {k: p.name for k, p in paths.items() if k != "json"},
    }


ALIAS = re.compile(r"[A-Za-z0-9_-]{1,255}")
"""A registered model's alias, as MLflow takes it (and not ``latest`` nor ``v<digits>``, which
name versions)."""


def check_alias(alias: str | None) -> str | None:
    """``alias`` if MLflow can set it (or None), else a one-line LboError."""
    if alias is None:
        return None
    alias = str(alias)
    if not ALIAS.fullmatch(alias) or alias.lower() == "latest" or re.fullmatch(r"v\d+", alias):
        raise LboError(f"alias: expected letters, digits, _ and - (not 'latest' nor "
                       f"v<digits>, which name versions), got {alias!r}")
    return alias


def register(run_id: str, name: str, uri: str | None = None, alias: str | None = None) -> str:
    """Register run ``run_id``'s MLflow model (``model/``, :mod:`lbo.serve.serving`; a run trained
    before lbo logged one: its ``checkpoints/``) as a new version of model ``name``; with
    ``alias`` (e.g. ``champion``), point that alias of the model at the new version, so that
    ``models:/<name>@<alias>`` follows promotions.

    Returns the ``models:/<name>/<version>`` URI that :meth:`Observer.load`, ``python -m
    lbo.observe observer=...``, ``mlflow.pyfunc.load_model`` and ``mlflow models serve``
    accept.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    from lbo.core.paths import tracking_uri

    alias = check_alias(alias)  # before anything is registered

    uri = uri or tracking_uri()
    client = mlflow.MlflowClient(uri, registry_uri=uri)
    try:
        run = client.get_run(run_id)
        files = [a.path for a in client.list_artifacts(run_id, "checkpoints")]
        if "checkpoints/best.ckpt" not in files:
            raise LboError(f"register: MLflow run {run_id} has no checkpoints/best.ckpt")
        try:
            client.get_registered_model(name)
        except MlflowException:
            client.create_registered_model(name)
        model = "model" in {a.path for a in client.list_artifacts(run_id)}
        source = f"runs:/{run_id}/{'model' if model else 'checkpoints'}"
        version = client.create_model_version(name, source, run_id=run.info.run_id).version
        if alias is not None:
            client.set_registered_model_alias(name, alias, version)
    except MlflowException as e:
        raise LboError(f"register: {str(e.message).strip().splitlines()[0]}") from None
    return f"models:/{name}/{version}"


def export_observer(cfg: DictConfig) -> dict[str, Any]:
    """Export the configured observer; print the files and, with ``register``, the model URI."""
    from lbo.serve.observer import Observer
    from lbo.tracking.artifacts import RUN_ID

    if not cfg.get("observer"):
        raise LboError("observer: give a checkpoint path, an MLflow run id or a "
                       "models:/<name>/<version> URI")
    if not isinstance(cfg.observer, str):  # e.g. a run id of digits only
        raise LboError(f"observer: Hydra read {cfg.observer!r} as a number; quote it: "
                       "observer=\"'<run id>'\"")
    source = cfg.observer
    check_name(cfg.get("name"))  # before any checkpoint is read
    if cfg.get("register") and not RUN_ID.fullmatch(source):
        raise LboError(f"register needs observer=<MLflow run id> (32 hex digits), got {source!r}")
    alias = check_alias(cfg.get("alias"))
    if alias is not None and not cfg.get("register"):
        raise LboError("alias names a registered model's version: give register=<model name> "
                       "beside it")
    obs = Observer.load(source, features=cfg.get("features"), form=cfg.get("form"))
    paths = export(obs, cfg.out_dir, cfg.get("name"))
    diff = json.loads(paths["json"].read_text())["max_abs_diff_to_pytorch"]
    print(f"exported {obs.name} (window {obs.window}, dt {obs.dt:g} s, features {obs.features}, "
          f"{'recursive: one step' if obs.form == 'recursive' else 'window form'}); "
          f"max |diff| to PyTorch: TorchScript {diff['torchscript']:.1e}, "
          f"ONNX Runtime {diff['onnx']:.1e}")
    for kind, path in paths.items():
        print(f"  {kind:11s} {path}")
    result: dict[str, Any] = {"paths": paths, "diff": diff}
    if cfg.get("register"):
        result["model_uri"] = register(source, str(cfg.register), alias=alias)
        print(f"registered: {result['model_uri']}"
              + (f" (models:/{cfg.register}@{alias})" if alias is not None else ""))
    print(f"exported: {paths['onnx'].parent}")
    return result


main = entry("export", export_observer)


if __name__ == "__main__":
    sys.exit(main())

"""A trained observer as an MLflow model: ``mlflow.pyfunc.load_model`` and ``mlflow models
serve`` take it like any other model.

Every finished training run logs one, as ``runs:/<run id>/model`` (and ``python -m lbo.export
observer=<run id> register=<name>`` registers it). Its input is a log as a DataFrame with the
columns ``x_m, y_m, psi_m`` (m, m, rad; all three NaN or null where a step has no fix), ``V``
(m/s) and ``delta`` (rad), one row per sample at the observer's dt, oldest first; a window of N
rows is such a log, whose last row's estimate is the window's. An optional integer column
``log`` runs several logs independently in one call. A receiver's optional columns
(``sx_m, sy_m, spsi_m, ve_m, vn_m, sv_m, r_m``, :data:`lbo.sim.columns.RECEIVER`) are taken
as ``lbo.observe`` takes them, by an observer that reads them (the robust observer's recursive
form; ``psi_m`` may then be null on a row with a position). The output has one row per input row:
``x, y, psi`` (m, m, rad), ``valid``, and ``var_x, var_y, var_psi, cov_xy`` where the
observer knows its covariance (NaN for the CNN and the LSTM). The numbers are those of
``lbo.Observer.load(<the run>).run(...)``.

    import mlflow
    model = mlflow.pyfunc.load_model("runs:/<run id>/model")
    estimates = model.predict(log_frame)

    mlflow models serve -m runs:/<run id>/model --env-manager local -h 127.0.0.1 -p 5001
    curl -X POST 127.0.0.1:5001/invocations -H 'Content-Type: application/json' \\
         -d '{"dataframe_split": {"columns": ["x_m", "y_m", "psi_m", "V", "delta"], "data": [...]}}'
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from mlflow.pyfunc import PythonModel

from lbo.core.errors import LboError
from lbo.sim.columns import COVARIANCE, INPUT, MEAS, RECEIVER, SERVED, STATE, WINDOW

ARTIFACT = "model"
"""Where a training run logs its model: ``runs:/<run id>/model``."""
MAX_ROWS = 10_000
"""Most rows one request may hold (every ``log`` of it together): 200 s of a 50 Hz log. The
robust observer's PyTorch step took 1.3 to 2.3 ms a row where every row holds a fix (a busy
2-core machine), so the largest request is answered in 13 to 23 s, within MLflow's 60 s
request timeout (``MLFLOW_SCORING_SERVER_REQUEST_TIMEOUT``). A request past the timeout is
answered 504, but its worker runs on to the end: 10^6 rows held one at 100% CPU long after
the answer."""


def estimates(observer: Any, frame: pd.DataFrame) -> pd.DataFrame:
    """An observer's estimates over a log frame (:data:`WINDOW`, optionally ``log`` and the
    receiver's columns :data:`RECEIVER`), one output row per input row (:data:`SERVED`);
    raises LboError naming a missing column or a bad value, or a frame of more than
    :data:`MAX_ROWS` rows (before any work; MLflow answers it HTTP 400)."""
    if len(frame) > MAX_ROWS:
        raise LboError(f"model input: {len(frame)} rows, more than the {MAX_ROWS} one request "
                       f"may hold ({MAX_ROWS * 0.02:g} s at 50 Hz); send a longer log in parts "
                       f"of at most {MAX_ROWS} rows (each starts its observer afresh), or run "
                       "it with python -m lbo.observe or lbo.Observer.run, which take any length")
    missing = [c for c in WINDOW if c not in frame.columns]
    if missing:
        raise LboError(f"model input: missing column{'s' if len(missing) > 1 else ''} "
                       f"{', '.join(missing)} (a log needs {', '.join(WINDOW)}, one "
                       "row per sample)")
    groups = frame.groupby("log", sort=False).indices.values() if "log" in frame.columns \
        else [np.arange(len(frame))]
    out = np.full((len(frame), 7), np.nan)
    valid = np.zeros(len(frame), bool)
    for rows in groups:
        part = frame.iloc[rows]
        m = part[list(MEAS)].to_numpy(dtype=float)
        u = part[list(INPUT)].to_numpy(dtype=float)
        r = part.reindex(columns=list(RECEIVER)).to_numpy(dtype=float)
        found = observer.run(m, u, source="model input",
                             receiver=r if np.isfinite(r).any() else None)
        out[rows, :3] = found.state
        out[rows, 3:] = found.cov[:, [0, 1, 2, 0], [0, 1, 2, 1]]
        valid[rows] = found.valid
    result = pd.DataFrame(out, columns=[*STATE, *COVARIANCE])
    result.insert(len(STATE), "valid", valid)
    return result[list(SERVED)]


class ServedModel(PythonModel):
    """A learned observer's checkpoint behind MLflow's pyfunc interface (:func:`estimates`).

    MLflow loads it as model code (``lbo/serve/serving_model.py``), not as a pickle, so a model
    logged by one lbo loads in another as long as lbo and the checkpoint format agree."""

    def load_context(self, context: Any) -> None:
        from lbo.serve.observer import Observer

        self.observer = Observer.load(context.artifacts["checkpoint"])

    def predict(self, context: Any, model_input: pd.DataFrame,
                params: dict[str, Any] | None = None) -> pd.DataFrame:
        """:func:`estimates` of ``model_input``; a request lbo refuses (too many rows, a bad
        value) raises MLflow's invalid-parameter error with lbo's line as its message, which
        ``mlflow models serve`` answers HTTP 400 (any other exception: 400 with a generic
        message, lbo's line only in the stack trace)."""
        from mlflow.exceptions import MlflowException

        self.observer.reset()
        try:
            return estimates(self.observer, pd.DataFrame(model_input))
        except LboError as e:
            raise MlflowException.invalid_parameter_value(str(e)) from None


def signature() -> Any:
    """The model's input and output schema (columns and types)."""
    from mlflow.models import ModelSignature
    from mlflow.types import ColSpec, Schema

    # one list display: Schema takes a list of ColSpec or TensorSpec
    inputs = Schema([*(ColSpec("double", c) for c in WINDOW),
                     ColSpec("long", "log", required=False),
                     *(ColSpec("double", c, required=False) for c in RECEIVER)])
    outputs = Schema([ColSpec("boolean" if c == "valid" else "double", c)
                      for c in SERVED])
    return ModelSignature(inputs=inputs, outputs=outputs)


def log_model(tracking_uri: str, run_id: str, checkpoint: str | Path) -> str:
    """Save ``checkpoint`` as a pyfunc model and log it under ``model/`` of MLflow run
    ``run_id`` in ``tracking_uri``, and as a logged model of that run (MLflow 3's Models tab
    and the run's page list it, named after the run); returns its ``runs:/<run id>/model``
    URI. Only the client API: no run is started or ended, and MLflow's global tracking URI is
    left alone."""
    import tempfile
    import warnings
    from importlib.metadata import version

    import mlflow

    from lbo.tracking.runs import no_progress_bar

    # saving copies the checkpoint in through MLflow's downloader: no bars after the result
    with tempfile.TemporaryDirectory(prefix="lbo-model-") as tmp, warnings.catch_warnings(), \
            no_progress_bar():
        # the signature names every column; an example would cost a model load per run
        warnings.filterwarnings("ignore", message=".*input example was not provided")
        folder = Path(tmp) / ARTIFACT
        mlflow.pyfunc.save_model(
            str(folder), python_model=str(Path(__file__).with_name("serving_model.py")),
            artifacts={"checkpoint": str(checkpoint)}, signature=signature(),
            # lbo and its pinned torch: --env-manager local serves from this environment
            pip_requirements=[f"lbo=={version('lbo')}", "torch==2.13.0"])
        client = mlflow.MlflowClient(tracking_uri)
        client.log_artifacts(run_id, str(folder), ARTIFACT)
        run = client.get_run(run_id).info
        # a logged model's name may not hold / : . % " ' (a run's name may: a study's trials)
        name = re.sub(r"""[/:.%"']""", "_", run.run_name or "") or "observer"
        model = client.create_logged_model(run.experiment_id, name=name,
                                           source_run_id=run_id, model_type="lbo observer")
        client.log_model_artifacts(model.model_id, str(folder))
        client.finalize_logged_model(model.model_id, "READY")
    return f"runs:/{run_id}/{ARTIFACT}"

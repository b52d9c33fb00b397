"""The served model's cap on a request's rows (issue 68): 10^6 rows to ``mlflow models serve``
were answered 504 after 60 s while the worker ran on at 100% CPU; now a request of more than
``MAX_ROWS`` rows is refused before any work, and MLflow answers it HTTP 400 with lbo's line.
No server is started: the pyfunc model's ``predict`` and MLflow's request handler are called
directly."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from mlflow.exceptions import MlflowException
from mlflow.pyfunc import scoring_server

from lbo.serve.observer import Observer
from lbo.serve.serving import MAX_ROWS, ServedModel
from lbo.sim.columns import SERVED, WINDOW

LINE = (rf"^model input: {MAX_ROWS + 1} rows, more than the {MAX_ROWS} one request may hold "
        rf"\(200 s at 50 Hz\); send a longer log in parts of at most {MAX_ROWS} rows")


class _Untouched:
    """An observer that fails the test if a refused request reaches it."""

    def reset(self) -> None:
        pass

    def run(self, *args: object, **kwargs: object) -> None:
        raise AssertionError("the model worked on a request it refuses")


def _frame(rows: int) -> pd.DataFrame:
    """A log standing still at the origin with a full fix on every row."""
    return pd.DataFrame(np.zeros((rows, len(WINDOW))), columns=list(WINDOW))


def test_a_request_of_more_rows_than_the_cap_is_refused_before_any_work():
    model = ServedModel()
    model.observer = _Untouched()
    with pytest.raises(MlflowException, match=LINE) as e:
        model.predict(None, _frame(MAX_ROWS + 1))
    assert e.value.get_http_status_code() == 400 and "\n" not in e.value.message
    # through MLflow's request handler, as `mlflow models serve` takes a posted CSV
    stub = SimpleNamespace(predict=lambda data, params=None: model.predict(None, data),
                           metadata=None)
    with pytest.raises(MlflowException) as e:
        scoring_server.invocations(_frame(MAX_ROWS + 1).to_csv(index=False), "text/csv", stub,
                                   None)
    assert e.value.get_http_status_code() == 400
    assert f"{MAX_ROWS + 1} rows, more than the {MAX_ROWS} one request may hold" in e.value.message


def test_a_request_at_the_cap_is_answered():
    model = ServedModel()
    model.observer = Observer.load("ekf")
    out = model.predict(None, _frame(MAX_ROWS))
    assert list(out.columns) == list(SERVED) and len(out) == MAX_ROWS and out["valid"].all()

"""The model code MLflow runs to load a learned observer (``lbo.serve.serving``); not imported by
lbo itself."""

from mlflow.models import set_model

from lbo.serve.serving import ServedModel

set_model(ServedModel())

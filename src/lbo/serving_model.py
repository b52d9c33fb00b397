"""The model code MLflow runs to load a learned observer (``lbo.serving``); not imported by
lbo itself."""

from mlflow.models import set_model

from lbo.serving import ObserverModel

set_model(ObserverModel())

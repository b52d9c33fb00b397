"""Everything Optuna: the search spaces and samplers (``search``), the study's storage and its
connections (``storage``), the study mirrored in MLflow (``mirror``), the hand-off of the best
parameters as a config (``handoff``) and the pruning and trial callbacks (``callbacks``).
Above ``tracking``: a study's runs are MLflow runs."""

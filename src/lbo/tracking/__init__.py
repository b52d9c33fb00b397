"""Where runs and studies are stored: MLflow runs, Optuna storage and its MLflow mirror, and the
search spaces."""

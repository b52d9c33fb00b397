"""Where runs are stored: MLflow stores and servers, the checkpoints a run holds, and the runs
table each experiment keeps for mlflow ui (a study's storage: lbo.tuning)."""

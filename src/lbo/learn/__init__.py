"""Training: the noise draws, the data module, the Lightning module, the evaluation callback,
the run's builders, the ETA and checkpoints written whole."""

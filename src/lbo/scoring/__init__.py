"""Scores: the metrics, the test-grid evaluation of any observer, scores on a user's logs, and
the report."""

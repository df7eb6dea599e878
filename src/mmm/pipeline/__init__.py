"""Pipelines: stages chained as one MLflow parent run with a nested run per step."""

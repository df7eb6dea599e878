"""Packaging trained models for the MLflow Model Registry and serving."""

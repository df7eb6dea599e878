"""Evaluation: text-motion evaluators, metrics and speed measurements."""

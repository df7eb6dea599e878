"""MMM: generative masked motion model for text-to-motion, trained with Lightning and tracked in MLflow."""

__version__ = "0.1.0"

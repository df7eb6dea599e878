"""The bundle's model as code (MLflow's models from code): `log_bundle` logs this file, and loading
a bundle runs it, instead of unpickling a `TextToMotionPyfunc` object (a pickle can run any code
when loaded; this file is plain source, copied into the bundle, and MLflow may refuse pickles)."""

import mlflow

from mmm.registry.bundle import TextToMotionPyfunc

mlflow.models.set_model(TextToMotionPyfunc())

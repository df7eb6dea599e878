"""Everything about the package is in pyproject.toml; this file only ships conf/ inside the wheel.

The configs live at the repository's top level (conf/, beside src/), which a wheel would leave
out: an installed `mmm` could then compose no config outside a checkout. Building copies them to
mmm/conf in the wheel, where `mmm.config.conf_dir` finds them. An editable install reads the
checkout's conf/ directly, so nothing is copied for it.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

CONF = Path(__file__).resolve().parent / "conf"


class BuildPyWithConf(build_py):
    def run(self):
        super().run()
        if self.editable_mode:
            return
        if not CONF.is_dir():  # an sdist always carries it (MANIFEST.in); a bare src/ tree does not
            raise FileNotFoundError(f"{CONF}: the configs the package ships are missing from the source tree")
        target = Path(self.build_lib) / "mmm" / "conf"
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(CONF, target, ignore=shutil.ignore_patterns("*.pyc", "__pycache__"))


setup(cmdclass={"build_py": BuildPyWithConf})

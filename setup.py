"""UPS's optional compiled fast path.

By default the package is pure Python. With ``UPS_COMPILE=1`` in the environment, mypyc
compiles the modules of the TCP/IP event path (``[tool.ups] compiled`` in pyproject.toml) to C
extensions from the same source; an extension module is imported in place of its ``.py``.
Needs a C compiler and the Python headers; the in-tree build backend (``_build/backend.py``)
adds mypy to the build's requirements. Everything else is in pyproject.toml.

    UPS_COMPILE=1 pip install .                        # a compiled install
    UPS_COMPILE=1 python setup.py build_ext --inplace  # compiled modules beside the sources
"""

import os
import tomllib
from pathlib import Path

from setuptools import setup


def _ext_modules() -> list:  # type: ignore[type-arg]
    if os.environ.get("UPS_COMPILE") != "1" or os.environ.get("UPS_FINDING_REQUIREMENTS"):
        return []
    from mypyc.build import mypycify

    config = tomllib.loads(Path(__file__).with_name("pyproject.toml").read_text())
    return mypycify(config["tool"]["ups"]["compiled"], opt_level="3", multi_file=True)


setup(ext_modules=_ext_modules())

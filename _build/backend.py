"""setuptools' build backend, plus mypy when ``UPS_COMPILE=1`` asks for the compiled build."""

import os

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F403  (the backend's whole interface)

_MYPYC = ["mypy>=1.10"]


def _extra() -> list[str]:
    return _MYPYC if os.environ.get("UPS_COMPILE") == "1" else []


def get_requires_for_build_wheel(config_settings=None):  # type: ignore[no-untyped-def]
    return _setuptools.get_requires_for_build_wheel(config_settings) + _extra()


def get_requires_for_build_editable(config_settings=None):  # type: ignore[no-untyped-def]
    return _setuptools.get_requires_for_build_editable(config_settings) + _extra()

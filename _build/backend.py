"""setuptools' build backend, plus mypy when ``UPS_COMPILE=1`` asks for the compiled build."""

import os

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F403  (the backend's whole interface)

_MYPYC = ["mypy>=1.10"]


def _extra() -> list[str]:
    return _MYPYC if os.environ.get("UPS_COMPILE") == "1" else []


def _requires(hook, config_settings):  # type: ignore[no-untyped-def]
    # setuptools runs setup.py to find its requirements, before mypy is installed: it is told
    # not to compile yet
    os.environ["UPS_FINDING_REQUIREMENTS"] = "1"
    try:
        return hook(config_settings) + _extra()
    finally:
        del os.environ["UPS_FINDING_REQUIREMENTS"]


def get_requires_for_build_wheel(config_settings=None):  # type: ignore[no-untyped-def]
    return _requires(_setuptools.get_requires_for_build_wheel, config_settings)


def get_requires_for_build_editable(config_settings=None):  # type: ignore[no-untyped-def]
    return _requires(_setuptools.get_requires_for_build_editable, config_settings)

"""The optional parts of UPS (its extras), the one line that says how to install a missing one,
and the one that puts ``ups`` on a new shell's PATH.

UPS itself needs python-can, msgpack and cryptography. The rest is optional, by extra:
``zenoh`` (eclipse-zenoh: ``Node(zenoh=...)``, ``--zenoh``, ``ups zenoh-router``), ``tools``
(rich, aiohttp, cantools: ``ups monitor``'s live screen, ``ups console``, ``ups dbc``),
``bench`` (the peers ``ups bench`` measures against, and matplotlib for its plots) and ``fast``
(uvloop, used when installed). A part that is missing raises ``ConfigError`` saying what to
install, the way that works here: in a checkout (an editable install of this repository) the
checkout's own pip, ``.venv/bin/pip install -e '.[zenoh]'``; elsewhere
``pip install 'ups-pubsub[zenoh]'``.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import sys
from pathlib import Path

from ._errors import ConfigError

DISTRIBUTION = "ups-pubsub"  #: the name UPS is installed by


def require(module: str, extra: str, missing: str, otherwise: str = "") -> None:
    """Raise ``ConfigError`` when ``module`` (of the extra ``extra``) is not installed: one line,
    ``missing`` (what is not installed, "Zenoh is not installed (eclipse-zenoh)"), the command
    that installs it, and ``otherwise`` (" (or give --plain)")."""
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent package missing, or a broken entry
        found = False
    if not found:
        raise ConfigError(f"{missing}: {install_hint(extra)}{otherwise}")


def install_hint(extra: str) -> str:
    """The command that installs ``extra`` into this Python: in a checkout its pip with
    ``-e '<checkout>[extra]'``, else ``pip install 'ups-pubsub[extra]'``."""
    root = checkout()
    if root is None:
        return f"pip install '{DISTRIBUTION}[{extra}]'"
    pip = Path(sys.executable).with_name("pip")  # else an environment without a pip script:
    installer = _shown(pip) if pip.exists() else f"{_shown(Path(sys.executable))} -m pip"
    return f"{installer} install -e '{_shown(root)}[{extra}]'"


def activation() -> str | None:
    """What to type in a new shell before ``ups ...`` runs this installation: ``source
    .venv/bin/activate`` (the path as seen from here), or None when the ``ups`` on the PATH is
    this installation's already (or none can be told: ``ups`` not beside this Python)."""
    bin_dir = Path(sys.executable).parent
    ours = bin_dir / "ups"
    if not ours.exists():
        return None
    found = shutil.which("ups")
    if found is not None and Path(found).resolve() == ours.resolve():
        return None
    activate = bin_dir / "activate"
    if activate.exists():
        return f"source {_shown(activate)}"
    return f'export PATH="{bin_dir}:$PATH"'


def checkout() -> Path | None:
    """The repository UPS runs from, when it runs from a checkout (an editable install, or the
    sources on ``sys.path``); None when it was installed from a wheel."""
    root = Path(__file__).resolve().parent.parent
    try:
        project = (root / "pyproject.toml").read_text(encoding="utf-8")
    except OSError:
        return None
    return root if f'name = "{DISTRIBUTION}"' in project else None


def _shown(path: Path) -> str:
    """``path`` as a person types it here: relative to the working directory when inside it."""
    try:
        relative = os.path.relpath(path)
    except ValueError:  # another drive (Windows)
        return str(path)
    if relative == ".":
        return "."
    return relative if not relative.startswith("..") else str(path)

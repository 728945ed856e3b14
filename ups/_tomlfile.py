"""Reading the TOML files UPS takes (catalogs, ACLs, the JAUS, ROS 2 and EtherCAT maps): one
reader, so that every one refuses the same bad files with one line instead of a traceback or a
hang.

A file is read only when it is a regular file of at most ``MAX_BYTES`` (``/dev/zero`` or a FIFO
would be read forever, a huge file would fill memory), as UTF-8; TOML nested deeper than the
interpreter can parse (tomllib parses nested arrays and inline tables by recursion) is refused
as too deep. Each refusal is a ``ConfigError`` that names the file.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

from ._errors import ConfigError

MAX_BYTES = 4 << 20  #: the largest TOML file read (a catalog of 4096 channels is ~1 MiB)


def read_toml(path: str | Path, what: str) -> tuple[str, dict[str, Any]]:
    """The text of the TOML file at ``path`` and what it holds; ``what`` names the kind of
    file in errors ("the catalog", "the ACL", ...)."""
    text = read_text(path, what)
    return text, parse_toml(text, f"{what} {path}")


def read_text(path: str | Path, what: str) -> str:
    """The text of a regular UTF-8 file of at most ``MAX_BYTES``, or a ``ConfigError``."""
    try:
        # O_NONBLOCK: opening a FIFO nobody writes to would wait forever (a regular file
        # ignores the flag)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        with open(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise ConfigError(f"cannot read {what} {path}: not a regular file")
            data = f.read(MAX_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    if len(data) > MAX_BYTES:
        raise ConfigError(f"cannot read {what} {path}: larger than {MAX_BYTES >> 20} MiB")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"cannot read {what} {path}: not UTF-8 ({exc.reason})") from None


def parse_toml(text: str, source: str) -> dict[str, Any]:
    """TOML ``text``; ``source`` names it in a ``ConfigError`` ("the catalog robots.toml")."""
    import tomllib  # only when a file is read: ups --help stays quick

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{source}: nested too deep to read") from None

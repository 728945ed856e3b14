"""Child-process entry point: pin the CPU, import the peer module, run one role."""

from __future__ import annotations

import importlib
import os
import traceback
from multiprocessing.connection import Connection
from typing import Any

from ups.benchmarks.peers import Link


class PipeControl:
    """The :class:`benchmarks.peers.Control` of a child: messages over its pipe end."""

    def __init__(self, conn: Connection) -> None:
        self._conn = conn

    def ready(self) -> None:
        """Tell the harness that the other side may start now."""
        self._conn.send(("ready", None))

    def wait_release(self, timeout: float = 60.0) -> bool:
        """Block until the harness sends ``release``; False on timeout or a closed pipe."""
        try:
            return bool(self._conn.poll(timeout)) and self._conn.recv() == "release"
        except (EOFError, OSError):
            return False


def run_role(
    module: str, role: str, link: Link, kwargs: dict[str, Any], pin: int | None, conn: Connection
) -> None:
    """Run ``<module>.run_<role>(link, ctl, **kwargs)`` and send its result up the pipe.

    Sends ``("ready", None)`` when the role says so, then ``("result", value)`` or
    ``("error", traceback_text)``. With ``pin`` set, the process is bound to that CPU
    first, before the peer's library is imported or starts any thread.
    """
    if pin is not None:
        os.sched_setaffinity(0, {pin})
    try:
        peer = importlib.import_module(module)
        result = getattr(peer, f"run_{role}")(link, PipeControl(conn), **kwargs)
        conn.send(("result", result))
    except BaseException:
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()

"""Which network a node joins: the one its options name, and the face built for it.

Each kind of network's face lives in a module of its own (``_canface``, ``_tcpface``,
``_zenohface``), with ``OPTIONS`` (the node options it takes) and ``build(where, context,
**options)``; it is imported only when a node of that kind starts: a TCP/IP node does not load
python-can.
"""

from __future__ import annotations

import importlib
from typing import Any

from ._errors import ConfigError
from ._face import Face, FaceContext

#: the module of each kind of network's face
FACES = {"can": "._canface", "broker": "._tcpface", "zenoh": "._zenohface"}


def choose(
    can: Any, broker: str | None, zenoh: str | None, zenoh_config: object
) -> tuple[str, Any]:
    """The one network that a node's options name, as ``(kind, where)``: ``ConfigError`` unless
    there is exactly one (a Zenoh config file names where to connect by itself)."""
    networks = {
        kind: where
        for kind, where in (("can", can), ("broker", broker), ("zenoh", zenoh))
        if where is not None
    }
    if zenoh_config is not None:
        networks.setdefault("zenoh", "")
    if len(networks) != 1:
        raise ConfigError(
            "a node needs one network: Node(can='INTERFACE:CHANNEL'), "
            "Node(broker='HOST:PORT') or Node(zenoh='tcp/HOST:PORT')"
        )
    ((kind, where),) = networks.items()
    return kind, where


def build_face(kind: str, where: Any, context: FaceContext, options: dict[str, Any]) -> Face:
    """The face of the ``kind`` network at ``where``, built with ``options`` (the node's options
    that were given): ``ConfigError`` for one that is not an option of this kind of network."""
    module = importlib.import_module(FACES[kind], __package__)
    stray = set(options) - module.OPTIONS
    if stray:
        raise ConfigError(f"{', '.join(sorted(stray))}: not an option of {kind} nodes")
    face: Face = module.build(where, context, **options)
    return face

"""The UPS gateway: one ECH with a CAN face and an IP face, TCP/IP or Zenoh (``ups gateway``)."""

from ._gateway import Gateway
from ._serve import serve

__all__ = ["Gateway", "serve"]

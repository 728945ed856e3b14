"""The UPS gateway: one ECH with a CAN face and a TCP face (``ups gateway``)."""

from ._gateway import Gateway, serve

__all__ = ["Gateway", "serve"]

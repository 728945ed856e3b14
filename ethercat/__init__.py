"""UPS on EtherCAT (issue 34): the EtherCAT master side of a UPS node, with pysoem (SOEM).

Built so far: :func:`scan` (``ups ethercat scan``), which finds the slaves of a segment and
reads what each says it is. The master's errors are :class:`EthercatError`. ``docs/ethercat.md``
says what exists and what does not yet.
"""

from ._master import EthercatError, SlaveInfo, scan

__all__ = ["EthercatError", "SlaveInfo", "scan"]

"""UPS on EtherCAT (issue 34): a UPS node that is the EtherCAT master of a segment (pysoem,
SOEM inside), its slaves' process data mapped onto UPS channels by a map file.

:func:`scan` (``ups ethercat scan``) finds the slaves of a segment and reads what each says it
is; :func:`load_map` reads and checks a map (``ups ethercat check``); :class:`Segment` is the
master and its cycle on a thread of its own; :class:`EthercatNode` connects a segment to a
UPS node (``ups ethercat --ifname IF --map FILE``). The master's errors are
:class:`EthercatError`, a map's :class:`MapError`. ``docs/ethercat.md`` says what each does.
"""

from ._bridge import EthercatNode
from ._cycle import Segment
from ._map import EthercatMap, MapError, load_map
from ._master import EthercatError, SlaveInfo, scan

__all__ = [
    "EthercatError",
    "EthercatMap",
    "EthercatNode",
    "MapError",
    "Segment",
    "SlaveInfo",
    "load_map",
    "scan",
]

"""Real-time analysis of CAN message sets: response times, priority assignment, simulation.

``analyze`` bounds worst-case response times (``davis2007``, the revised analysis of Davis,
Burns, Bril and Lukkien, by default; ``tindell1994`` for the computation behind Table 1 of
paper 000). ``deadline_monotonic`` and ``audsley`` order messages, ``to_priority_field`` maps an
ordering onto the 8-bit UPS priority field and ``assign_priorities`` does both as an admission
test that raises ``NotSchedulable`` naming the message that would miss its deadline.
``simulate`` replays a set on a bit-accurate model of CAN arbitration. ``frame_bits`` gives
frame lengths; ``load_csv`` reads a message set.
"""

from ._analysis import Blocking, Method, analyze
from ._frames import Stuffing, frame_bits
from ._model import MessageSpec, NotSchedulable, Result, load_csv
from ._priority import Policy, assign_priorities, audsley, deadline_monotonic, to_priority_field
from ._sim import Jitter, Observation, SimStuffing, simulate

__all__ = [
    "Blocking",
    "Jitter",
    "MessageSpec",
    "Method",
    "NotSchedulable",
    "Observation",
    "Policy",
    "Result",
    "SimStuffing",
    "Stuffing",
    "analyze",
    "assign_priorities",
    "audsley",
    "deadline_monotonic",
    "frame_bits",
    "load_csv",
    "simulate",
    "to_priority_field",
]

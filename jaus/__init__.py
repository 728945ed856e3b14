"""A JAUS codec: pure functions, no I/O.

- JUDP, the SAE AS5669A JAUS UDP transport (port 3794): :func:`decode_judp` turns a datagram
  into :class:`JudpMessage` objects, :func:`encode_judp` does the reverse, :func:`split_message`
  cuts a large message into parts and :class:`Reassembler` puts parts back together.
- The older JAUS Reference Architecture 3.3 framing (``JAUS01.0`` and a 16-byte header):
  :func:`decode_ra33` and :func:`encode_ra33`.
- The message codes of the core (AS5710A) and mobility (AS6009) services
  (:class:`MessageCode`), payload codecs for a few of them (:func:`decode_payload`) and JAUS
  scaled integers (:func:`to_scaled`, :func:`from_scaled`).

Every decoder raises :class:`JausDecodeError`, and nothing else, for bad bytes. Unknown message
codes are not errors: messages carry their code and payload bytes. ``docs/jaus.md`` describes
every byte and where its layout comes from.
"""

from ._codec import AckNak, JausDecodeError, JausId, from_scaled, to_scaled
from ._codes import MessageCode, message_name
from ._judp import (
    DEFAULT_PART_SIZE,
    JUDP_PORT,
    JUDP_VERSION,
    Broadcast,
    DataFlags,
    HcFlags,
    JudpHeader,
    JudpMessage,
    Priority,
    decode_judp,
    encode_judp,
    split_message,
)
from ._payloads import (
    ConfirmControl,
    ControlResponse,
    IdentificationType,
    Payload,
    QueryAuthority,
    QueryControl,
    QueryGlobalPose,
    QueryHeartbeatPulse,
    QueryIdentification,
    QueryType,
    RejectControl,
    RejectResponse,
    ReleaseControl,
    ReportAuthority,
    ReportControl,
    ReportGlobalPose,
    ReportHeartbeatPulse,
    ReportIdentification,
    RequestControl,
    SetAuthority,
    SetWrenchEffort,
    TimeStamp,
    decode_payload,
    encode_payload,
)
from ._ra33 import (
    RA33_PREFIX,
    Ra33Address,
    Ra33DataFlags,
    Ra33Header,
    Ra33Message,
    decode_ra33,
    encode_ra33,
)
from ._reassembly import Reassembler, ReassemblyCounts

__all__ = [
    "DEFAULT_PART_SIZE",
    "JUDP_PORT",
    "JUDP_VERSION",
    "RA33_PREFIX",
    "AckNak",
    "Broadcast",
    "ConfirmControl",
    "ControlResponse",
    "DataFlags",
    "HcFlags",
    "IdentificationType",
    "JausDecodeError",
    "JausId",
    "JudpHeader",
    "JudpMessage",
    "MessageCode",
    "Payload",
    "Priority",
    "QueryAuthority",
    "QueryControl",
    "QueryGlobalPose",
    "QueryHeartbeatPulse",
    "QueryIdentification",
    "QueryType",
    "Ra33Address",
    "Ra33DataFlags",
    "Ra33Header",
    "Ra33Message",
    "Reassembler",
    "ReassemblyCounts",
    "RejectControl",
    "RejectResponse",
    "ReleaseControl",
    "ReportAuthority",
    "ReportControl",
    "ReportGlobalPose",
    "ReportHeartbeatPulse",
    "ReportIdentification",
    "RequestControl",
    "SetAuthority",
    "SetWrenchEffort",
    "TimeStamp",
    "decode_judp",
    "decode_payload",
    "decode_ra33",
    "encode_judp",
    "encode_payload",
    "encode_ra33",
    "from_scaled",
    "message_name",
    "split_message",
    "to_scaled",
]

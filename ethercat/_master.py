"""The EtherCAT master, over pysoem (SOEM): open the interface, find the slaves, read their
identity from the SII EEPROM and the sizes of their process data.

pysoem is imported inside the functions that need it (the ``ethercat`` extra), so that importing
this module costs nothing and a missing pysoem is one clear line from ``ups._extras``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from ups._errors import UpsError

STATES = {1: "INIT", 2: "PRE-OP", 3: "BOOT", 4: "SAFE-OP", 8: "OP"}
ERROR_FLAG = 0x10
#: AL status codes by name (ETG.1000.6 Table 11): the ones a master meets when bringing
#: simple I/O slaves up; others are shown as a number
AL_STATUS_CODES = {
    0x0000: "no error",
    0x0001: "unspecified error",
    0x0011: "invalid requested state change",
    0x0012: "unknown requested state",
    0x0013: "bootstrap not supported",
    0x0014: "no valid firmware",
    0x0016: "invalid mailbox configuration",
    0x0017: "invalid sync manager configuration",
    0x0018: "no valid inputs available",
    0x0019: "no valid outputs",
    0x001A: "synchronization error",
    0x001B: "sync manager watchdog",
    0x001D: "invalid output configuration",
    0x001E: "invalid input configuration",
    0x0020: "slave needs cold start",
    0x0021: "slave needs INIT",
    0x0022: "slave needs PRE-OP",
    0x0023: "slave needs SAFE-OP",
}
SCAN_TIMEOUT_US = 2_000_000  #: how long a slave may take to reach PRE-OP during a scan


class EthercatError(UpsError):
    """The EtherCAT segment cannot be used: the interface, no slave, a slave refusing a state."""


def state_name(status: int) -> str:
    """An AL status register's state, ``PRE-OP`` or ``SAFE-OP+ERROR``."""
    name = STATES.get(status & 0x0F, f"0x{status & 0x0F:x}")
    return f"{name}+ERROR" if status & ERROR_FLAG else name


def al_code_name(code: int) -> str:
    return f"0x{code:04x} ({AL_STATUS_CODES.get(code, 'see ETG.1000.6 Table 11')})"


@dataclass(frozen=True)
class SlaveInfo:
    """One slave as found: its position (from 1), identity, AL state and process data sizes."""

    position: int
    vendor: int
    product: int
    revision: int
    name: str
    state: str
    al_status_code: int
    outputs: int  #: bytes the master writes
    inputs: int  #: bytes the slave returns

    def as_json(self) -> dict[str, Any]:
        return asdict(self)


def open_master(ifname: str) -> Any:
    """A pysoem master on ``ifname``, opened (raw socket: root or CAP_NET_RAW)."""
    import pysoem

    master = pysoem.Master()
    try:
        master.open(ifname)
    except (ConnectionError, OSError) as exc:
        raise EthercatError(
            f"cannot open {ifname} for EtherCAT: {exc} (an interface that exists, and root or "
            "CAP_NET_RAW)"
        ) from exc
    return master


def scan(ifname: str) -> list[SlaveInfo]:
    """The slaves on ``ifname``, in line order. Like any master's scan, this takes over the
    segment: every slave is reset to INIT, its process data sized from its SII (SyncManagers
    and FMMUs set as for a run), then asked for PRE-OP and no further; ``state`` is what it
    reached. Raises ``EthercatError`` when no slave answers."""
    master = open_master(ifname)
    try:
        master.manual_state_change = True  # config_map sizes the slaves: no SAFE-OP request
        found = master.config_init()
        if found <= 0:
            raise EthercatError(f"no EtherCAT slave answers on {ifname}")
        master.config_map()
        for slave in master.slaves:
            slave.state = 2  # PRE-OP
            slave.write_state()
        master.state_check(2, SCAN_TIMEOUT_US)
        master.read_state()
        return [
            SlaveInfo(
                position=n,
                vendor=slave.man,
                product=slave.id,
                revision=slave.rev,
                name=slave.name.decode(errors="replace")
                if isinstance(slave.name, bytes)
                else str(slave.name),
                state=state_name(slave.state),
                al_status_code=slave.al_status,
                outputs=len(slave.output),
                inputs=len(slave.input),
            )
            for n, slave in enumerate(master.slaves, 1)
        ]
    finally:
        master.close()

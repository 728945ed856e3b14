"""One emulated EtherCAT slave controller (ESC) and the application behind it.

The ESC is its register and process RAM space (``MEMORY`` bytes) with the behaviour a master
relies on: the configured station address (0x0010), DL status (0x0110), AL control and status
with the status code (0x0120, 0x0130, 0x0134), the SII EEPROM interface (0x0500-0x050F, 8-byte
reads), the FMMUs (0x0600) and the SyncManagers (0x0800). Writes to read-only registers are
ignored, as an ESC ignores them.

``datagram`` applies one datagram as it passes (ETG.1000.4): auto-increment addressing (ADP
incremented by every slave, addressed at 0), configured addressing, broadcast, and logical
addressing through the FMMUs, with the working counter rules: +1 read, +1 written (+2 for the
write of a read/write command), so +3 for a slave that does both in one LRW or APRW/FPRW.
Logical access to a SyncManager's area counts only while that SyncManager is enabled and the
slave is in SAFE-OP or OP, as a slave whose application has not enabled it.

The application is the AL state machine: INIT, PRE-OP, SAFE-OP, OP (BOOT is refused), with
the AL status codes of ETG.1000.6 Table 11 for a refused transition, the error flag held until
the master acknowledges it. In OP the application takes the output SyncManager's bytes as its
outputs; outside OP its outputs are all zero (safe). An optional SyncManager watchdog drops OP
to SAFE-OP with code 0x001B when outputs stop coming.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable

from ._sii import INPUT_START, OUTPUT_START, Identity, eeprom

MEMORY = 0x2000  #: registers (0x0000-0x0FFF) and 4 KiB of process RAM

INIT, PREOP, BOOT, SAFEOP, OP = 1, 2, 3, 4, 8
STATE_NAMES = {INIT: "INIT", PREOP: "PRE-OP", BOOT: "BOOT", SAFEOP: "SAFE-OP", OP: "OP"}
ERROR_FLAG = 0x10

# AL status codes (ETG.1000.6 Table 11) the emulator reports
AL_INVALID_STATE_CHANGE = 0x0011
AL_UNKNOWN_STATE = 0x0012
AL_BOOTSTRAP_NOT_SUPPORTED = 0x0013
AL_SM_WATCHDOG = 0x001B
AL_INVALID_OUTPUT_CONFIG = 0x001D
AL_INVALID_INPUT_CONFIG = 0x001E

# registers
STADR, ALIAS, DLCTL, DLSTAT = 0x0010, 0x0012, 0x0100, 0x0110
ALCTL, ALSTAT, ALSTATCODE = 0x0120, 0x0130, 0x0134
EEPCFG, EEPCTL, EEPADR, EEPDAT = 0x0500, 0x0502, 0x0504, 0x0508
FMMU0, SM0 = 0x0600, 0x0800
FMMU_COUNT, SM_COUNT = 8, 8

EEP_READ = 0x0100  #: command bits 8-10 of EEPCTL
EEP_R64 = 0x0040  #: status: reads return 8 bytes
EEP_ERROR_COMMAND = 0x2000

#: registers (ranges, end excluded) a master may write; every other register is read-only
WRITABLE = (
    (STADR, 0x0014), (DLCTL, 0x0104), (ALCTL, 0x0122), (0x0200, 0x0204), (0x0300, 0x0314),
    (EEPCFG, 0x0502), (EEPCTL, 0x0510), (FMMU0, 0x0700), (SM0, 0x0880), (0x0900, 0x0A00),
    (0x1000, MEMORY),
)  # fmt: skip

APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(1, 15)
READS = {APRD, FPRD, BRD, LRD, APRW, FPRW, BRW, LRW, ARMW, FRMW}
WRITES = {APWR, FPWR, BWR, LWR, APRW, FPRW, BRW, LRW, ARMW, FRMW}
COMMAND_NAMES = dict(enumerate((
    "NOP", "APRD", "APWR", "APRW", "FPRD", "FPWR", "FPRW", "BRD", "BWR", "BRW", "LRD", "LWR",
    "LRW", "ARMW", "FRMW",
)))  # fmt: skip


def _writable(address: int) -> bool:
    return any(low <= address < high for low, high in WRITABLE)


class Slave:
    """One slave: an ESC and its application. ``on_change(slave, what)`` is called when the
    application's outputs (``"outputs"``) or the AL status (``"state"``) change."""

    def __init__(
        self,
        identity: Identity,
        *,
        watchdog: float = 0.0,
        on_change: Callable[[Slave, str], None] | None = None,
    ) -> None:
        self.identity = identity
        self.sii = eeprom(identity)
        self.memory = bytearray(MEMORY)
        self.watchdog = watchdog  #: seconds without outputs in OP before SAFE-OP + 0x001B; 0 off
        self.on_change = on_change
        self.outputs = bytes(identity.outputs)  #: what the application drives now
        self.inputs = bytearray(identity.inputs)  #: what the application reads (set by tests)
        self.last_output_write = 0.0
        self.counts: dict[str, int] = {}
        struct.pack_into("<BBHBBHB", self.memory, 0, 0x11, 1, 1, FMMU_COUNT, SM_COUNT, 4, 0x0F)
        struct.pack_into("<H", self.memory, 0x0008, 0x0000)  # features: no DC
        struct.pack_into("<H", self.memory, ALIAS, identity.alias)
        struct.pack_into("<H", self.memory, EEPCTL, EEP_R64)
        self._set_al(INIT, 0)
        self.last_slave = True

    # --- what tests and the chain look at ----------------------------------------------------

    @property
    def state(self) -> int:
        return self.memory[ALSTAT] & 0x0F

    @property
    def al_status(self) -> tuple[int, bool, int]:
        """(state, error flag, AL status code)."""
        status, code = self.memory[ALSTAT], struct.unpack_from("<H", self.memory, ALSTATCODE)[0]
        return status & 0x0F, bool(status & ERROR_FLAG), code

    @property
    def station(self) -> int:
        return int(struct.unpack_from("<H", self.memory, STADR)[0])

    def set_link(self, last: bool) -> None:
        """DL status: port 0 open with a link, and port 1 too unless this is the last slave."""
        self.last_slave = last
        struct.pack_into("<H", self.memory, DLSTAT, 0x0230 if last else 0x0A30)

    def _count(self, what: str) -> None:
        self.counts[what] = self.counts.get(what, 0) + 1

    # --- the datagram as it passes -------------------------------------------------------------

    def datagram(
        self, command: int, adp: int, ado: int, data: bytearray, wkc: int
    ) -> tuple[int, int]:
        """Apply one datagram (data changed in place); returns the ADP to pass on and the WKC."""
        self._count(COMMAND_NAMES.get(command, "unknown"))
        if command in (APRD, APWR, APRW, ARMW):
            if adp == 0:
                wkc += self._physical(command, ado, data)
            elif command == ARMW:
                wkc += self._physical(APWR, ado, data)
            return (adp + 1) & 0xFFFF, wkc
        if command in (FPRD, FPWR, FPRW, FRMW):
            if adp == self.station:
                wkc += self._physical(command, ado, data)
            elif command == FRMW:
                wkc += self._physical(FPWR, ado, data)
            return adp, wkc
        if command in (BRD, BWR, BRW):
            return (adp + 1) & 0xFFFF, wkc + self._physical(command, ado, data, broadcast=True)
        if command in (LRD, LWR, LRW):
            return adp, wkc + self._logical(command, adp | ado << 16, data)
        return adp, wkc  # NOP and unknown commands pass untouched

    def _physical(self, command: int, address: int, data: bytearray, *, broadcast: bool = False
                  ) -> int:  # fmt: skip
        """Read and/or write at a physical address; for a read/write command the datagram
        returns what was there before the write."""
        end = min(address + len(data), MEMORY)
        reads = command in READS
        writes = command in WRITES and command not in (ARMW, FRMW)  # the addressed one reads
        old = b""
        if reads:
            self._before_read(address, end)
            old = bytes(self.memory[address:end]) + bytes(len(data) - (end - address))
        if writes:
            self._write(address, bytes(data[: end - address]))
        if reads:
            if broadcast:  # BRD, BRW: every slave ORs its bytes in
                data[:] = bytes(a | b for a, b in zip(data, old, strict=True))
            else:
                data[:] = old
        return int(reads) + (2 if reads and writes else int(writes))

    def _logical(self, command: int, logical: int, data: bytearray) -> int:
        read = written = False
        for n in range(FMMU_COUNT):
            log_start, log_len, _sb, _eb, phys, _pb, kind, active = struct.unpack_from(
                "<IHBBHBBB", self.memory, FMMU0 + 16 * n
            )
            if not active or not log_len:
                continue
            low, high = max(logical, log_start), min(logical + len(data), log_start + log_len)
            if low >= high:
                continue
            start = phys + (low - log_start)
            where = slice(low - logical, high - logical)
            if kind == 1 and command in (LRD, LRW) and self._process_data(start, high - low):
                self._before_read(start, start + high - low)
                data[where] = self.memory[start : start + high - low]
                read = True
            elif kind == 2 and command in (LWR, LRW) and self._process_data(start, high - low):
                self.memory[start : start + high - low] = data[where]
                written = True
        if written:
            self._outputs_written()
        return int(read) + (2 if written and command == LRW else int(written))

    def _process_data(self, start: int, length: int) -> bool:
        """Whether an enabled SyncManager covers [start, start + length) in SAFE-OP or OP."""
        if self.state not in (SAFEOP, OP):
            return False
        for n in range(SM_COUNT):
            phys, size, _control, _status, activate, _pdi = struct.unpack_from(
                "<HHBBBB", self.memory, SM0 + 8 * n
            )
            if activate & 1 and size and phys <= start and start + length <= phys + size:
                return True
        return False

    # --- registers with behaviour ------------------------------------------------------------

    def _before_read(self, start: int, end: int) -> None:
        if start < INPUT_START + len(self.inputs) and end > INPUT_START:
            self.memory[INPUT_START : INPUT_START + len(self.inputs)] = self.inputs

    def _write(self, address: int, data: bytes) -> None:
        touched = set()
        for offset, byte in enumerate(data):
            where = address + offset
            if _writable(where):
                self.memory[where] = byte
                touched.add(where)
        if ALCTL in touched:
            self._al_control(struct.unpack_from("<H", self.memory, ALCTL)[0])
        if EEPCTL + 1 in touched:
            self._eeprom_command()
        if touched & set(range(OUTPUT_START, OUTPUT_START + self.identity.outputs)):
            self._outputs_written()

    def _eeprom_command(self) -> None:
        control = struct.unpack_from("<H", self.memory, EEPCTL)[0]
        status = EEP_R64
        if control & 0x0700 == EEP_READ:
            word = struct.unpack_from("<I", self.memory, EEPADR)[0]
            chunk = self.sii[word * 2 : word * 2 + 8]
            self.memory[EEPDAT : EEPDAT + 8] = chunk + b"\xff" * (8 - len(chunk))
            self._count("eeprom_reads")
        elif control & 0x0700:
            status |= EEP_ERROR_COMMAND  # writes and reloads are not emulated
        struct.pack_into("<H", self.memory, EEPCTL, status)

    def _set_al(self, state: int, code: int) -> None:
        before = self.al_status if self.memory[ALSTAT] else None
        self.memory[ALSTAT] = state | (ERROR_FLAG if code else 0)
        struct.pack_into("<H", self.memory, ALSTATCODE, code)
        if state != OP:
            self._apply_outputs(bytes(self.identity.outputs))
        if before is not None and before != self.al_status and self.on_change is not None:
            self.on_change(self, "state")

    def _al_control(self, control: int) -> None:
        requested, ack = control & 0x0F, bool(control & ERROR_FLAG)
        current, error, code = self.al_status
        if error and not ack:
            if requested == INIT:  # INIT is always taken
                self._set_al(INIT, code)
            return  # an error stands until acknowledged
        if requested == INIT:
            self._set_al(INIT, 0)
        elif requested == BOOT:
            self._set_al(current, AL_BOOTSTRAP_NOT_SUPPORTED)
        elif requested not in STATE_NAMES:
            self._set_al(current, AL_UNKNOWN_STATE)
        elif requested == current or requested < current:
            self._set_al(requested, 0)  # same state, or down (OP -> SAFE-OP, ... -> PRE-OP)
        elif (current, requested) == (INIT, PREOP):
            self._set_al(PREOP, 0)
        elif (current, requested) == (PREOP, SAFEOP):
            problem = self._sm_problem()
            self._set_al(PREOP if problem else SAFEOP, problem)
        elif (current, requested) == (SAFEOP, OP):
            self.last_output_write = time.monotonic()
            self._set_al(OP, 0)
        else:
            self._set_al(current, AL_INVALID_STATE_CHANGE)

    def _sm_problem(self) -> int:
        """The AL status code for SyncManagers not set as the SII says (0: they are)."""
        for n, (start, size, code) in enumerate((
            (OUTPUT_START, self.identity.outputs, AL_INVALID_OUTPUT_CONFIG),
            (INPUT_START, self.identity.inputs, AL_INVALID_INPUT_CONFIG),
        )):  # fmt: skip
            phys, length, _control, _status, activate, _pdi = struct.unpack_from(
                "<HHBBBB", self.memory, SM0 + 8 * n
            )
            if size and (phys != start or length != size or not activate & 1):
                return code
        return 0

    # --- the application ---------------------------------------------------------------------

    def _outputs_written(self) -> None:
        self.last_output_write = time.monotonic()
        if self.state == OP:
            size = self.identity.outputs
            self._apply_outputs(bytes(self.memory[OUTPUT_START : OUTPUT_START + size]))

    def _apply_outputs(self, outputs: bytes) -> None:
        if outputs != self.outputs:
            self.outputs = outputs
            if self.on_change is not None:
                self.on_change(self, "outputs")

    def tick(self, now: float) -> None:
        """The SyncManager watchdog: OP without outputs for ``watchdog`` s -> SAFE-OP, 0x001B."""
        if self.watchdog and self.state == OP and now - self.last_output_write > self.watchdog:
            self._set_al(SAFEOP, AL_SM_WATCHDOG)

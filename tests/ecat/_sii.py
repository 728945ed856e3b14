"""The SII EEPROM image of an emulated slave (ETG.1000.6 / ETG.2010): the ESC configuration
area with its CRC, the identity (vendor, product, revision, serial), no mailbox, then the
categories a master reads: strings (1: the device name), general, FMMU, SyncM, TxPDO, RxPDO.

Process data is byte-wide: the RxPDO 0x1600 maps ``outputs`` entries of 8 bits (0x7000:1..n)
onto SM0 at 0x1000, the TxPDO 0x1A00 maps ``inputs`` entries (0x6000:1..n) onto SM1 at
``INPUT_START``. Words are little-endian, as everything on EtherCAT.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

OUTPUT_START, INPUT_START = 0x1000, 0x1100  #: physical addresses of the two process data SMs
SM_OUTPUT_CONTROL, SM_INPUT_CONTROL = 0x64, 0x20  #: buffered; ECAT writes (watchdog) / reads
EEPROM_BYTES = 1024

CAT_STRINGS, CAT_GENERAL, CAT_FMMU, CAT_SM, CAT_TXPDO, CAT_RXPDO, CAT_END = (
    10, 30, 40, 41, 50, 51, 0xFFFF,
)  # fmt: skip


@dataclass(frozen=True)
class Identity:
    """What the slave says it is, and the sizes of its process data (bytes, 0 to 64)."""

    vendor: int
    product: int
    revision: int
    name: str
    outputs: int
    inputs: int
    serial: int = 0
    alias: int = 0

    def __post_init__(self) -> None:
        for what in ("outputs", "inputs"):
            if not 0 <= getattr(self, what) <= 64:
                raise ValueError(f"{what}: 0 to 64 bytes, not {getattr(self, what)}")
        if not self.name or len(self.name.encode()) > 64:
            raise ValueError(f"a name of 1 to 64 bytes, not {self.name!r}")


def crc8(data: bytes) -> int:
    """The ESC configuration area's checksum: CRC-8, polynomial x^8 + x^2 + x + 1, from 0xFF."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", kind, len(data) // 2) + data


def _pdo(index: int, sm: int, entry_index: int, count: int) -> bytes:
    """One PDO of ``count`` 8-bit entries ``entry_index:1..count`` (USINT), on SyncM ``sm``."""
    head = struct.pack("<HBBBBH", index, count, sm, 0, 0, 0)
    entries = b"".join(
        struct.pack("<HBBBBH", entry_index, sub, 0, 0x05, 8, 0) for sub in range(1, count + 1)
    )
    return head + entries


def eeprom(identity: Identity) -> bytes:
    """The whole EEPROM, padded with 0xFF to ``EEPROM_BYTES``."""
    config = struct.pack("<HHHHH", 0x0005, 0, 0, 0, identity.alias) + bytes(4)  # PDI: none
    config += struct.pack("<H", crc8(config))
    info = struct.pack(
        "<IIII", identity.vendor, identity.product, identity.revision, identity.serial
    )
    head = config + info + bytes(8)  # words 0x08-0x13
    head += bytes(8)  # 0x14-0x17: bootstrap mailbox (none)
    head += bytes(10)  # 0x18-0x1C: standard mailbox (none: offsets and sizes 0, no protocol)
    head += bytes(0x3E * 2 - len(head))
    head += struct.pack("<HH", EEPROM_BYTES * 8 // 1024 - 1, 1)  # size (Kbit - 1), version 1
    name = identity.name.encode()
    strings = bytes([1, len(name)]) + name
    general = bytes([0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0]) + struct.pack("<hBBHH", 0, 0, 0, 0, 0)
    general += bytes(32 - len(general))
    fmmus = bytes([1, 2])  # FMMU0 outputs, FMMU1 inputs
    sms = b"".join(  # start, length, control, status, enable, type (3 outputs, 4 inputs)
        struct.pack("<HHBBBB", start, size, control, 0, 1 if size else 0, kind)
        for start, size, control, kind in (
            (OUTPUT_START, identity.outputs, SM_OUTPUT_CONTROL, 3),
            (INPUT_START, identity.inputs, SM_INPUT_CONTROL, 4),
        )
    )
    body = _category(CAT_STRINGS, strings) + _category(CAT_GENERAL, general)
    body += _category(CAT_FMMU, fmmus) + _category(CAT_SM, sms)
    if identity.inputs:
        body += _category(CAT_TXPDO, _pdo(0x1A00, 1, 0x6000, identity.inputs))
    if identity.outputs:
        body += _category(CAT_RXPDO, _pdo(0x1600, 0, 0x7000, identity.outputs))
    image = head + body + struct.pack("<H", CAT_END)
    if len(image) > EEPROM_BYTES:
        raise ValueError(f"the SII needs {len(image)} bytes, more than {EEPROM_BYTES}")
    return image + b"\xff" * (EEPROM_BYTES - len(image))

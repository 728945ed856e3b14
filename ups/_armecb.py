"""libups-ecb as a board runs it: the CAN-ECB's Cortex-M0+ image (``ecb-full`` or ``ecb-small``
of ``make -C c size``) in the emulator of ``ups._armnode`` (its ``Mcu``).

``ArmEcb`` is the emulated backend of ``ups.broker.c_ecb.CEcb`` (``ups c-ecb --target m0``):
each method one call of ``c/ups_ecb.h`` executed as the board executes it, the ``ups_ecb_t``,
the frame, the configuration and the blob in the emulated RAM. A call that faults (an
unaligned access, one outside the image's flash and RAM, a write to flash: ``Fault``, with the
address and the instruction) or runs past its budget of instructions (``OverBudget``: ``budget``,
or ``tables_budget`` for the calls over the whole tables, init, save and restore) raises
``Stopped``, which names the call: the one error of ``errors``, what the daemon stops on.

The sizes of the image's tables (and of ``ups_ecb_t``, its frame, its counters, its blob) are
the compiler's, for the image's own configuration (the ``UPS_...`` macros ``build_image`` wrote
beside it): a declaration of each as an array, compiled beside the image, read back with
``nm -S`` (as ``state_size`` reads ``ups_ecb_t``). So any image ``build_image`` linked runs,
a test's build with sources of its own among them.
"""

from __future__ import annotations

import fcntl
import struct
from pathlib import Path

from ._armnode import (
    CPU,
    Fault,
    Mcu,
    OverBudget,
    _defines,
    _run,
    _size_py,
    build_image,
    state_size,
)
from ._cnode import C_DIR
from ._errors import ConfigError

BUILDS = {"full": "ecb-full", "small": "ecb-small"}  #: ``--build`` -> c/size.py's image
BUDGET = 20_000_000  #: instructions one call may run (0.4 s and more at 48 MHz: a board's
#: watchdog would have reset it long before); a DECLARE's admission test over the 32 streams
#: of ecb-full can run past it (c/README.md's cycles table): it is stopped, not waited for
TABLES_BUDGET = 256  #: instructions per pair of table entries, (channels + nodes)², that the
#: calls over the whole tables (ups_ecb_init, _save, _restore) may run, and at least BUDGET:
#: restore checks each entry of a blob against those taken before, about 19 (ecb-full) to 30
#: (ecb-small) per pair for a full blob; 256 leaves a factor of 8 (ecb-full: 104 million)

#: what the image's sizes are read as: name -> the C expression of its size in bytes (plus
#: one, so that a table of none is still an array)
_LIMITS = {
    "nodes": "UPS_ECB_NODES", "channels": "UPS_ECB_CHANNELS", "streams": "UPS_ECB_STREAMS",
    "queries": "UPS_ECB_QUERIES", "tx_depth": "UPS_ECB_TX_DEPTH", "held": "UPS_ECB_HELD",
    "watched": "UPS_ECB_WATCHED", "counter_bytes": "sizeof(UPS_ECB_COUNTER_T)",
    "blob_max": "UPS_ECB_BLOB_MAX", "mtu": "UPS_MTU", "rosters": "UPS_ECB_ROSTERS",
    "frame": "sizeof(ups_frame_t)",
    "counters": "sizeof(ups_ecb_counters_t)", "cfg": "sizeof(ups_ecb_config_t)",
}  # fmt: skip


class Stopped(Exception):
    """A call of the image faulted or ran past its budget: ``cause`` is the ``Fault`` (with its
    address) or ``OverBudget``."""

    def __init__(self, call: str, cause: Fault | OverBudget) -> None:
        super().__init__(str(cause) if isinstance(cause, OverBudget) else f"{call}: {cause}")
        self.cause = cause


def limits(elf: Path) -> dict[str, int]:
    """The sizes of ``_LIMITS`` for the image ``elf`` (linked by ``build_image``)."""
    out = elf.parent
    obj = out / "limits.o"
    if not (out / "state.o").exists():
        raise ConfigError(f"{elf} was not linked by ups._armnode.build_image (no state.o beside)")
    source = '#include "ups_ecb.h"\n' + "".join(
        f"char ups_limit_{n}[({e}) + 1];\n" for n, e in _LIMITS.items())  # fmt: skip
    written = out / "limits.c"

    def stale() -> bool:  # older than the image, or of other _LIMITS
        return (not obj.exists() or obj.stat().st_mtime < elf.stat().st_mtime
                or not written.exists() or written.read_text() != source)  # fmt: skip

    if stale():  # (a fresh one is only read: an image's folder may be read-only)
        with open(out / ".lock", "w") as lock:  # build_image's: one process writes at a time
            fcntl.flock(lock, fcntl.LOCK_EX)
            if stale():
                _build_limits(elf, out, written, source)
    found = {}
    for line in _run("arm-none-eabi-nm", "-S", obj.name, cwd=out).splitlines():
        fields = line.split()
        if len(fields) == 4 and fields[3].startswith("ups_limit_"):
            found[fields[3].removeprefix("ups_limit_")] = int(fields[1], 16) - 1
    return found


def _build_limits(elf: Path, out: Path, written: Path, source: str) -> None:
    """Compile ``source`` (written to ``written``) with the image's flags into out/limits.o."""
    size = _size_py()
    defines = [f"-D{name}={value}" for name, value in _defines(elf).items()]
    written.write_text(source)
    _run("arm-none-eabi-gcc", *size.CPUS[CPU], *size.FLAGS, *defines, f"-I{C_DIR}",
         "-fno-common", "-c", written.name, "-o", "limits.o.tmp", cwd=out)  # fmt: skip
    (out / "limits.o.tmp").replace(out / "limits.o")


class ArmEcb:
    """libups-ecb's ``build`` image ("full": ecb-full, a bus of 127 nodes; "small": ecb-small)
    on an emulated Cortex-M0+: the backend ``CEcb`` drives (``ups.broker.c_ecb.Backend``)."""

    errors = (Stopped,)  #: what a call raises when the image stopped

    def __init__(
        self,
        build: str = "full",
        *,
        budget: int = BUDGET,
        elf: Path | None = None,
        count: bool = False,
    ) -> None:
        """``elf``: an image of ``build_image``'s to run instead of ``build``'s; ``count``: the
        emulator counts each call's cycles (``Mcu``: c/cycles.py's measure)."""
        self.elf = elf or build_image(BUILDS[build])
        self.name = f"{BUILDS[build] if elf is None else elf} on an emulated {CPU}"
        self.budget = budget
        sizes = limits(self.elf)
        self.tables_budget = max(budget, TABLES_BUDGET * (sizes["channels"] + sizes["nodes"]) ** 2)
        self.config = {k: sizes[k] for k in ("nodes", "channels", "streams", "queries",
                                             "tx_depth", "held", "watched", "counter_bytes",
                                             "blob_max", "mtu", "rosters")}  # fmt: skip
        self._count = sizes["counters"] // sizes["counter_bytes"]
        self._counter = {2: "H", 4: "I", 8: "Q"}[sizes["counter_bytes"]]
        ecb = state_size(self.elf, "ecb")
        self.mcu = mcu = Mcu(self.elf, ecb + sizes["frame"] + sizes["cfg"] + sizes["blob_max"]
                             + 32 + 64, count=count)  # fmt: skip
        self._at_ecb = mcu.alloc(ecb)
        self._at_frame = mcu.alloc(sizes["frame"], 4)
        self._at_cfg = mcu.alloc(sizes["cfg"], 4)
        self._at_word = mcu.alloc(8, 8)  # a uint64_t the table's readers write
        self._at_users = mcu.alloc(32, 4)  # ups_ecb_channel_users' subscribers, publishers
        self._at_blob = mcu.alloc(sizes["blob_max"], 4)
        self._cfg_size = sizes["cfg"]

    def _call(self, name: str, *args: int, wide: tuple[int, ...] = (), tables: bool = False) -> int:
        """``tables``: a call over the whole tables, which runs within ``tables_budget``."""
        try:
            budget = self.tables_budget if tables else self.budget
            value = self.mcu.call(name, *args, wide=wide, budget=budget)
        except (Fault, OverBudget) as exc:
            raise Stopped(name, exc) from exc
        return value - (1 << 32) if value & 0x8000_0000 else value

    def default_config(self) -> bytes:
        self._call("ups_ecb_default_config", self._at_cfg)
        return self.mcu.read(self._at_cfg, self._cfg_size)

    def init(self, cfg: bytes, instance: int) -> int:
        self.mcu.write(self._at_cfg, cfg)
        return self._call(
            "ups_ecb_init", self._at_ecb, self._at_cfg, instance, wide=(2,), tables=True
        )

    def restore(self, blob: bytes) -> int:
        if len(blob) > self.config["blob_max"]:
            return -1  # larger than the tables: what ups_ecb_restore refuses too
        self.mcu.write(self._at_blob, blob)
        return self._call("ups_ecb_restore", self._at_ecb, self._at_blob, len(blob), tables=True)

    def start(self, now: int) -> None:
        self._call("ups_ecb_start", self._at_ecb, now)

    def rx(self, now: int, can_id: int, flags: int, data: bytes) -> None:
        self.mcu.write(self._at_frame, struct.pack("<IBB", can_id, flags, len(data)) + data)
        self._call("ups_ecb_rx", self._at_ecb, now, self._at_frame)

    def tick(self, now: int) -> None:
        self._call("ups_ecb_tick", self._at_ecb, now)

    def notes(self) -> int:
        return self._call("ups_ecb_notes", self._at_ecb)

    def pop_tx(self) -> tuple[int, int, bytes] | None:
        frame = self._call("ups_ecb_tx_peek", self._at_ecb)
        if frame == 0:
            return None
        can_id, flags, length = struct.unpack("<IBB", self.mcu.read(frame, 6))
        data = self.mcu.read(frame + 6, length)
        self._call("ups_ecb_tx_pop", self._at_ecb)
        return can_id, flags, data

    def save(self) -> bytes:
        n = self._call(
            "ups_ecb_save", self._at_ecb, self._at_blob, self.config["blob_max"], tables=True
        )
        return self.mcu.read(self._at_blob, n) if n > 0 else b""

    def role(self) -> int:
        return self._call("ups_ecb_role", self._at_ecb)

    def counters(self) -> tuple[int, ...]:
        at = self._call("ups_ecb_counters", self._at_ecb) & 0xFFFF_FFFF
        width = self.config["counter_bytes"]
        return struct.unpack(f"<{self._count}{self._counter}",
                             self.mcu.read(at, width * self._count))  # fmt: skip

    def node(self, i: int) -> tuple[int, int]:
        txnode = self._call("ups_ecb_node", self._at_ecb, i, self._at_word)
        return txnode, struct.unpack("<Q", self.mcu.read(self._at_word, 8))[0]

    def channel(self, i: int) -> tuple[int, int]:
        etag = self._call("ups_ecb_channel", self._at_ecb, i, self._at_word)
        return etag, struct.unpack("<Q", self.mcu.read(self._at_word, 8))[0]

    def channel_users(self, i: int) -> tuple[int, int, int]:
        at = self._at_users
        etag = self._call("ups_ecb_channel_users", self._at_ecb, i, at, at + 16)
        users = self.mcu.read(at, 32)
        return etag, int.from_bytes(users[:16], "little"), int.from_bytes(users[16:], "little")


def arm_ecb(build: str, image: Path | None = None) -> ArmEcb:
    """``ArmEcb(build, elf=image)``; an ``image`` that is no CAN-ECB image of ``build_image``'s
    (not an ELF, cut short, a node's image, unreadable) is a ConfigError that says so, not a
    traceback."""
    try:
        return ArmEcb(build, elf=image)
    except ConfigError:
        raise
    except Exception as exc:  # pyelftools' ELFError and ELFParseError, OSError, a missing symbol
        if image is None:
            raise
        raise ConfigError(f"{image} is not a CAN-ECB image linked by ups._armnode.build_image "
                          f"({type(exc).__name__}: {exc})") from exc  # fmt: skip

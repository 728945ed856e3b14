"""libups as a board runs it: the Cortex-M0+ image under an instruction-set emulator (unicorn).

``build_image`` compiles and links the image exactly as ``make -C c size`` does for a board
(``c/size.py``: its compiler flags, its configurations, ``-nostdlib``, ``--gc-sections``, every
public function kept). ``Mcu`` loads it into an emulated Cortex-M0+ with a RAM of the test's
own, calls its public functions by the ARM calling convention (AAPCS: arguments in r0-r3, then
on the stack; 64-bit ones in an even register pair) and stops a call, raising ``Fault`` with the
address and the instruction, at any access outside the image's flash and RAM, any write to
flash, and any unaligned halfword or word access (the Cortex-M0+ faults on each; the emulator
itself would not). With ``count=True`` it counts instructions and cycles by the Cortex-M0+
timing table (``cycles``). ``ArmNode`` is ``ups._cnode.CNode`` on that image: ``ups c-node
--target m0`` and the tests drive it as they drive the host build.

Needs the ``emu`` extra (unicorn, pyelftools) and arm-none-eabi-gcc.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import re
import shutil
import struct
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import can

from ._cnode import (
    C_DIR,
    COUNTERS,
    ERRORS,
    FRAME_ERR,
    FRAME_EXT,
    FRAME_FD,
    FRAME_RTR,
    CNode,
    Event,
)
from ._errors import ConfigError

CPU = "cortex-m0plus"
FLASH = 0x0000_0000  #: the image links at 0x8000 (the toolchain's default), inside this map
RAM = 0x2000_0000  #: the node, the buffers the application passes, and the stack
STACK = 2048  #: bytes of stack the calls get (size.py's worst case is a few hundred)
RETURN = 0x000F_F000  #: a call returns here (a NOP outside the image)
MUL_CYCLES = 1  #: MULS: 1 cycle with the fast multiplier, 32 with the small one (the TRM's option)


class Fault(Exception):
    """The image did what faults on a Cortex-M0+ (or touched memory it has no business with)."""

    def __init__(self, what: str, address: int, pc: int, instruction: str) -> None:
        super().__init__(f"{what} at 0x{address:08x} by the instruction at 0x{pc:08x} "
                         f"({instruction})")  # fmt: skip
        self.what, self.address, self.pc = what, address, pc


class OverBudget(Exception):
    """A call ran longer than the instructions it was allowed (``Mcu.call(budget=...)``)."""


def _size_py() -> ModuleType:
    """c/size.py, the one place the board's flags and configurations are written."""
    spec = importlib.util.spec_from_file_location("ups_c_size", C_DIR / "size.py")
    if spec is None or spec.loader is None:
        raise ConfigError(f"{C_DIR / 'size.py'} is missing")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(*cmd: str, cwd: Path) -> str:
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, check=False)
    if done.returncode != 0:
        raise ConfigError(f"{' '.join(cmd[:2])} failed:\n{done.stderr.strip()}")
    return done.stdout


def build_image(config: str = "minimal", extra: tuple[Path, ...] = ()) -> Path:
    """The Cortex-M0+ image of ``config`` (one of c/size.py's builds: libups's configurations,
    ``ecb-small`` and ``ecb-full`` for libups-ecb, ``node+ecb``), built if missing or older than
    its sources, into ``c/build/emu/``: the ELF ``lib.elf`` beside ``state.o`` (the
    ``ups_node_t node`` and/or ``ups_ecb_t ecb`` a board places). ``extra`` adds C sources to
    the image (a test's build; their public ``ups_`` functions are kept too)."""
    if shutil.which("arm-none-eabi-gcc") is None:
        raise ConfigError("arm-none-eabi-gcc is not on PATH (Debian: gcc-arm-none-eabi)")
    size = _size_py()
    table = size.builds()
    if config not in table:
        raise ConfigError(f"no configuration {config!r} in c/size.py: {sorted(table)}")
    _, sources, defines, state = table[config]
    tag = hashlib.sha256(b"".join(Path(x).read_bytes() for x in extra)).hexdigest()[:8]
    out = C_DIR / "build" / "emu" / CPU / (f"{config}-{tag}" if extra else config)
    out.mkdir(parents=True, exist_ok=True)
    elf = out / "lib.elf"
    with open(out / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        inputs = [C_DIR / "size.py", C_DIR / "Makefile", *C_DIR.glob("ups*.[ch]"), *extra]
        if elf.exists() and elf.stat().st_mtime >= max(p.stat().st_mtime for p in inputs):
            return elf
        flags = [*size.CPUS[CPU], *size.FLAGS, *defines, f"-I{C_DIR}"]
        objects = []
        for src in (*sources, *extra):
            obj = out / Path(src).name.replace(".c", ".o")
            _run("arm-none-eabi-gcc", *flags, "-c", str(C_DIR / src), "-o", str(obj), cwd=out)
            objects.append(str(obj))
        (out / "state.c").write_text("".join(sorted(state, key=lambda s: not s.startswith("#"))))
        _run("arm-none-eabi-gcc", *flags, "-fno-common", "-c", "state.c", "-o", "state.o",
             cwd=out)  # fmt: skip
        public = sorted({m for o in objects for m in re.findall(
            r" T (ups_[a-z]\w*)$", _run("arm-none-eabi-nm", "-g", o, cwd=out), re.M)})  # fmt: skip
        _run("arm-none-eabi-gcc", *size.CPUS[CPU], "-nostdlib", "-Wl,--gc-sections",
             "-Wl,--entry=0", *(f"-Wl,--undefined={p}" for p in public), "-o", "lib.elf.tmp",
             *objects, "-lgcc", cwd=out)  # fmt: skip
        macros = _run("arm-none-eabi-gcc", *flags, "-E", "-dM", "-x", "c", "-", cwd=out)
        (out / "config.h").write_text(macros)
        (out / "lib.elf.tmp").replace(elf)
    return elf


# --- the Cortex-M0+ timing table (ARM DDI 0484C, table 3-1) -----------------------------------


def _timing(hw: int) -> tuple[int, str]:
    """(cycles when not a taken branch, kind) of a 16-bit Thumb instruction; kind "branch":
    conditional, one more cycle when taken."""
    top5, top4 = hw >> 11, hw >> 12
    if hw >> 10 == 0b010000:  # data processing: MULS is opcode 0b1101
        return (MUL_CYCLES if (hw >> 6) & 0xF == 0b1101 else 1), "alu"
    if hw >> 10 == 0b010001:  # ADD/CMP/MOV high registers, BX, BLX
        if (hw >> 8) & 0b11 == 0b11:
            return 2, "bx"
        op, rd = (hw >> 8) & 0b11, (hw & 0b111) | ((hw >> 4) & 0b1000)
        return (2, "jump") if op != 0b01 and rd == 15 else (1, "alu")
    if top5 == 0b01001 or top4 in (0b0101, 0b0110, 0b0111, 0b1000, 0b1001):
        return 2, "memory"  # LDR literal, register offset, immediate, halfword, SP-relative
    if hw >> 9 == 0b1011010:  # PUSH: 1 + N
        return 1 + bin(hw & 0x1FF).count("1"), "memory"
    if hw >> 9 == 0b1011110:  # POP: 1 + N, 3 + N with PC (the return)
        pc = (hw >> 8) & 1
        return 1 + bin(hw & 0xFF).count("1") + 3 * pc, "pop_pc" if pc else "memory"
    if top4 == 0b1100:  # STM, LDM: 1 + N
        return 1 + bin(hw & 0xFF).count("1"), "memory"
    if top4 == 0b1101 and (hw >> 8) & 0xF < 0b1110:  # B<cond>: 1, 2 when taken
        return 1, "branch"
    if top5 == 0b11100:  # B
        return 2, "jump"
    return 1, "alu"


@dataclass
class Counts:
    """Instructions and cycles of one call."""

    instructions: int = 0
    cycles: int = 0


class Mcu:
    """One emulated Cortex-M0+ with the image of ``elf`` in flash and ``ram`` bytes of RAM."""

    def __init__(self, elf: Path, ram: int, *, count: bool = False) -> None:
        try:  # untyped packages: Any
            uc: Any = importlib.import_module("unicorn")
            a: Any = importlib.import_module("unicorn.arm_const")
            elf_file: Any = importlib.import_module("elftools.elf.elffile").ELFFile
        except ImportError as exc:
            raise ConfigError("the emulator needs the emu extra: pip install "
                              "'ups-pubsub[emu]' (unicorn, pyelftools)") from exc  # fmt: skip
        self._uc_mod = uc
        self._a = a
        self.uc: Any = uc.Uc(uc.UC_ARCH_ARM, uc.UC_MODE_THUMB | uc.UC_MODE_MCLASS)
        self.uc.ctl_set_cpu_model(a.UC_CPU_ARM_CORTEX_M0)
        with open(elf, "rb") as fh:
            image = elf_file(fh)
            self.symbols = {s.name: int(s["st_value"]) for s in
                            image.get_section_by_name(".symtab").iter_symbols()}  # fmt: skip
            segments = [(int(s["p_vaddr"]), s.data()) for s in image.iter_segments()
                        if s["p_type"] == "PT_LOAD" and s["p_filesz"]]  # fmt: skip
        end = max(addr + len(data) for addr, data in segments)
        self.uc.mem_map(FLASH, (end + 0xFFF) & ~0xFFF, uc.UC_PROT_READ | uc.UC_PROT_EXEC)
        for addr, data in segments:
            self.uc.mem_write(addr, data)
        self.uc.mem_map(RETURN, 0x1000, uc.UC_PROT_READ | uc.UC_PROT_EXEC)
        self.uc.mem_write(RETURN, b"\x00\xbf")  # NOP
        self.ram_size = (ram + STACK + 0xFFF) & ~0xFFF
        self.uc.mem_map(RAM, self.ram_size, uc.UC_PROT_READ | uc.UC_PROT_WRITE)
        self._brk = RAM
        self.fault: Fault | None = None
        self.counts = Counts()
        self.worst: dict[str, Counts] = {}  #: with ``count``: each function's costliest call
        self._blocks: dict[tuple[int, int], tuple[int, int, bool]] = {}
        self._pending: int | None = None  # after a conditional branch: where it falls through
        self.uc.hook_add(uc.UC_HOOK_MEM_INVALID, self._on_invalid)
        self.uc.hook_add(uc.UC_HOOK_MEM_READ | uc.UC_HOOK_MEM_WRITE, self._on_access)
        if count:
            self.uc.hook_add(uc.UC_HOOK_BLOCK, self._on_block)

    # --- memory ------------------------------------------------------------------------------

    def alloc(self, size: int, align: int = 8) -> int:
        """Place ``size`` bytes in RAM (zeroed), below the stack."""
        at = (self._brk + align - 1) & ~(align - 1)
        if at + size > RAM + self.ram_size - STACK:
            raise ConfigError("the emulated RAM is full")
        self._brk = at + size
        self.uc.mem_write(at, bytes(size))
        return at

    def read(self, address: int, size: int) -> bytes:
        return bytes(self.uc.mem_read(address, size))

    def write(self, address: int, data: bytes) -> None:
        self.uc.mem_write(address, data)

    # --- calls -------------------------------------------------------------------------------

    def call(self, name: str, *args: int, wide: tuple[int, ...] = (), budget: int = 0) -> int:
        """Call public function ``name`` with 32-bit ``args``; the positions in ``wide`` are
        64-bit (an even register pair, or 8-byte aligned on the stack). Returns r0. With a
        ``budget`` of instructions, a call that would run longer is stopped and raises
        ``OverBudget`` (its counts so far in ``counts``)."""
        a = self._a
        words: list[int] = []
        for k, value in enumerate(args):
            if k in wide:
                if len(words) % 2 and len(words) < 4:
                    words.append(0)  # a 64-bit argument starts at an even register
                words += [value & 0xFFFFFFFF, (value >> 32) & 0xFFFFFFFF]
            else:
                words.append(value & 0xFFFFFFFF)
        sp = RAM + self.ram_size
        stacked = words[4:]
        sp -= 4 * len(stacked)
        sp &= ~7
        for k, value in enumerate(stacked):
            self.uc.mem_write(sp + 4 * k, struct.pack("<I", value))
        for reg, value in zip((a.UC_ARM_REG_R0, a.UC_ARM_REG_R1, a.UC_ARM_REG_R2,
                               a.UC_ARM_REG_R3), words, strict=False):  # fmt: skip
            self.uc.reg_write(reg, value)
        self.uc.reg_write(a.UC_ARM_REG_SP, sp)
        self.uc.reg_write(a.UC_ARM_REG_LR, RETURN | 1)
        self.fault = None
        self._pending = None
        self.counts = Counts()
        try:
            self.uc.emu_start(self.symbols[name] | 1, RETURN, count=budget)
        except self._uc_mod.UcError as exc:
            if self.fault is None:
                pc = int(self.uc.reg_read(a.UC_ARM_REG_PC))
                self.fault = Fault(str(exc), pc, pc, self._instruction(pc))
        self._settle(RETURN)
        if self.fault is not None:
            raise self.fault
        if budget and int(self.uc.reg_read(a.UC_ARM_REG_PC)) & ~1 != RETURN:
            raise OverBudget(f"{name} ran past {budget} instructions")
        if self.counts.instructions and self.counts.cycles > self.worst.get(name, Counts()).cycles:
            self.worst[name] = self.counts
        return int(self.uc.reg_read(a.UC_ARM_REG_R0))

    def _instruction(self, pc: int) -> str:
        try:
            hw = struct.unpack("<H", self.uc.mem_read(pc & ~1, 2))[0]
        except self._uc_mod.UcError:
            return "unreadable"
        return f"0x{hw:04x}"

    # --- hooks -------------------------------------------------------------------------------

    def _stop(self, what: str, address: int) -> None:
        if self.fault is None:
            pc = int(self.uc.reg_read(self._a.UC_ARM_REG_PC))
            self.fault = Fault(what, address, pc, self._instruction(pc))
        self.uc.emu_stop()

    def _on_invalid(self, _uc: Any, access: int, address: int, size: int, *_: Any) -> bool:
        uc = self._uc_mod
        what = "a write to flash" if access == uc.UC_MEM_WRITE_PROT else (
            f"a {size}-byte access outside flash and RAM")  # fmt: skip
        self._stop(what, address)
        return False

    def _on_access(self, _uc: Any, access: int, address: int, size: int, *_: Any) -> None:
        if size > 1 and address % min(size, 4):
            kind = "write" if access == self._uc_mod.UC_MEM_WRITE else "read"
            self._stop(f"an unaligned {size}-byte {kind} (a HardFault on Cortex-M0+)", address)
        elif RAM <= address < RAM + self.ram_size and address + size > RAM + self.ram_size:
            self._stop("an access past the end of RAM", address)

    def _on_block(self, _uc: Any, address: int, size: int, _: Any) -> None:
        """One basic block about to run: its instructions and cycles (decoded once). A block
        ends at a branch; a conditional one costs a cycle more when the next block is not the
        one right after it (taken)."""
        self._settle(address)
        block = self._blocks.get((address, size))
        if block is None:
            block = self._blocks[(address, size)] = self._decode(address, size)
        counts = self.counts
        counts.instructions += block[0]
        counts.cycles += block[1]
        self._pending = address + size if block[2] else None

    def _decode(self, address: int, size: int) -> tuple[int, int, bool]:
        raw = bytes(self.uc.mem_read(address, size))
        at, instructions, cycles, kind = 0, 0, 0, ""
        while at + 2 <= len(raw):
            hw = struct.unpack_from("<H", raw, at)[0]
            if hw >> 11 in (0b11101, 0b11110, 0b11111) and at + 4 <= len(raw):
                hw2 = struct.unpack_from("<H", raw, at + 2)[0]  # BL, or MSR/MRS/DMB/DSB/ISB
                n, kind, at = 3, ("call" if hw2 & 0xD000 == 0xD000 else "system"), at + 4
            else:
                (n, kind), at = _timing(hw), at + 2
            instructions += 1
            cycles += n
        return instructions, cycles, kind == "branch"

    def _settle(self, address: int) -> None:
        """The block before was a conditional branch: taken unless this one follows it."""
        if self._pending is not None:
            if address != self._pending:
                self.counts.cycles += 1
            self._pending = None


# --- libups's API on the image ----------------------------------------------------------------


def _defines(elf: Path) -> dict[str, str]:
    text = (elf.parent / "config.h").read_text()
    return dict(re.findall(r"^#define (UPS_\w+) (.*)$", text, re.M))


def state_size(elf: Path, name: str = "node") -> int:
    """sizeof the state ``name`` (``node``: ups_node_t, ``ecb``: ups_ecb_t) of an image."""
    out = _run("arm-none-eabi-nm", "-S", "state.o", cwd=elf.parent)
    found = re.search(rf"^\w+ (\w+) [BCb] {name}$", out, re.M)
    if found is None:
        raise ConfigError(f"{elf.parent / 'state.o'} has no {name}")
    return int(found.group(1), 16)


class ArmNode(CNode):
    """``ups._cnode.CNode`` on the Cortex-M0+ image of ``config`` in an emulator: every method,
    each one call of ``c/ups.h`` executed as the board executes it (so ``CNodeRunner`` and
    ``ups c-node`` run it as they run the host build; the host library is not loaded)."""

    def __init__(self, node_id: int, *, fd: bool = False, config: str = "minimal",
                 count: bool = False, elf: Path | None = None) -> None:  # fmt: skip
        self.elf = elf or build_image(config)
        d = _defines(self.elf)
        mtu = 64 if d.get("UPS_WITH_FD") == "1" else 8
        counter = 2 if d.get("UPS_COUNTER_T") == "uint16_t" else 4
        self.config = {"channels": int(d["UPS_CHANNELS"]), "tx_depth": int(d["UPS_TX_DEPTH"]),
                       "fd": int(d.get("UPS_WITH_FD", "0")), "mtu": mtu,
                       "counter_bytes": counter}  # fmt: skip
        if fd and mtu != 64:
            raise ConfigError("this libups image was built without CAN FD (UPS_WITH_FD)")
        self._frame_size = (6 + mtu + 3) & ~3
        self._largest = max(256, int(d.get("UPS_MAX_EVENT", "8")))
        self.mcu = Mcu(self.elf, state_size(self.elf) + self._frame_size + 64 + self._largest,
                       count=count)  # fmt: skip
        self._at_node = self.mcu.alloc(state_size(self.elf))
        self._at_frame = self.mcu.alloc(self._frame_size, 4)
        self._at_event = self.mcu.alloc(12, 4)
        self._at_scratch = self.mcu.alloc(self._largest, 4)  # publish data, filters
        self.node_id = node_id
        self._check(
            self._call("ups_init", self._at_node, node_id, 1 if fd else 0, wide=(1,)), "init"
        )

    def _call(self, name: str, *args: int, wide: tuple[int, ...] = ()) -> int:
        value = self.mcu.call(name, *args, wide=wide)
        return value - (1 << 32) if value & 0x8000_0000 else value

    @staticmethod
    def _check(result: int, what: str) -> int:
        if result < 0:
            raise ConfigError(f"ups_{what}: {ERRORS.get(result, result)}")
        return result

    # --- the frames ------------------------------------------------------------------------

    def start(self, now: int) -> None:
        self._call("ups_start", self._at_node, now)

    def rx(self, msg: can.Message, now: int) -> Event | None:
        flags = ((FRAME_EXT if msg.is_extended_id else 0) | (FRAME_FD if msg.is_fd else 0)
                 | (FRAME_RTR if msg.is_remote_frame else 0)
                 | (FRAME_ERR if msg.is_error_frame else 0))  # fmt: skip
        return self.rx_raw(msg.arbitration_id, bytes(msg.data), flags, now)

    def rx_raw(self, can_id: int, data: bytes, flags: int, now: int) -> Event | None:
        data = data[: self.config["mtu"]]  # a port drops longer frames; the caller's concern
        self.mcu.write(self._at_frame, struct.pack("<IBB", can_id & 0xFFFFFFFF, flags, len(data))
                       + data)  # fmt: skip
        if not self._call("ups_rx", self._at_node, now, self._at_frame, self._at_event):
            return None
        ptr, size, channel, priority, txnode = struct.unpack(
            "<IHBBB", self.mcu.read(self._at_event, 9)
        )
        return Event(channel, self.mcu.read(ptr, size), priority, txnode)

    def tick(self, now: int) -> None:
        self._call("ups_tick", self._at_node, now)

    def tx(self) -> Iterator[tuple[int, int, bytes]]:
        while True:
            frame = self._call("ups_tx_peek", self._at_node)
            if frame == 0:
                return
            can_id, flags, length = struct.unpack("<IBB", self.mcu.read(frame, 6))
            item = (can_id, flags, self.mcu.read(frame + 6, length))
            self._call("ups_tx_pop", self._at_node)
            yield item

    # --- state -----------------------------------------------------------------------------

    def notes(self) -> int:
        return self._call("ups_notes", self._at_node)

    def idle(self) -> bool:
        return bool(self._call("ups_idle", self._at_node))

    @property
    def join_state(self) -> int:
        return self._call("ups_join_state", self._at_node)

    @property
    def txnode(self) -> int | None:
        txnode = self._call("ups_txnode", self._at_node)
        return None if txnode < 0 else txnode

    def counters(self) -> dict[str, int]:
        width = self.config["counter_bytes"]
        raw = self.mcu.read(self._call("ups_counters", self._at_node), width * len(COUNTERS))
        values = struct.unpack(f"<{len(COUNTERS)}{'H' if width == 2 else 'I'}", raw)
        return dict(zip(COUNTERS, values, strict=True))

    def filters(self) -> list[tuple[int, int]]:
        most = min(self.config["channels"] + 1, 32)
        n = self._call("ups_filters", self._at_node, self._at_scratch, most)
        raw = self.mcu.read(self._at_scratch, 8 * min(n, most))
        return [struct.unpack_from("<II", raw, 8 * k) for k in range(min(n, most))]

    # --- channels --------------------------------------------------------------------------

    def subscribe(self, uid: int, now: int) -> int:
        return self._check(self._call("ups_subscribe", self._at_node, uid, now, wide=(1,)),
                           "subscribe")  # fmt: skip

    def advertise(self, uid: int, max_size: int, now: int) -> int:
        return self._check(self._call("ups_advertise", self._at_node, uid, max_size, now,
                                      wide=(1,)), "advertise")  # fmt: skip

    def unsubscribe(self, channel: int) -> None:
        self._check(self._call("ups_unsubscribe", self._at_node, channel), "unsubscribe")

    def publish(self, channel: int, data: bytes) -> int:
        if len(data) > self._largest:
            return -4  # UPS_ERR_TOO_LARGE: larger than the image's UPS_MAX_EVENT
        self.mcu.write(self._at_scratch, data)
        return self._call("ups_publish", self._at_node, channel, self._at_scratch, len(data))

    def set_priority(self, channel: int, priority: int) -> None:
        self._check(self._call("ups_set_priority", self._at_node, channel, priority),
                    "set_priority")  # fmt: skip

    def channel_priority(self, channel: int) -> int:
        return self._call("ups_channel_priority", self._at_node, channel)

    def channel_state(self, channel: int) -> int:
        return self._call("ups_channel_state", self._at_node, channel)

    def channel_etag(self, channel: int) -> int:
        return self._call("ups_channel_etag", self._at_node, channel) & 0xFFFF

    def declare(
        self, channel: int, size: int, period: int, deadline: int, jitter: int, now: int
    ) -> int:
        return self._call("ups_declare", self._at_node, channel, size, period, deadline, jitter,
                          now)  # fmt: skip

    def declaration_state(self, channel: int) -> int:
        return self._call("ups_declaration_state", self._at_node, channel)

"""libups-ecb, the CAN-ECB in C (``c/ups_ecb.h``), from Python: the loop a microcontroller
would run it in, on any python-can bus, over one of two backends.

``CEcb`` has the interface of the Python ``CanEcb`` that the tests and ``serve`` use (``start``,
``close``, ``instance``, ``txnodes``, ``etags``, ``stats``, ``status``, ``healthy``,
``standby``), so the conformance suite and ``ups c-ecb`` run either. It feeds every frame its
link receives to ``ups_ecb_rx`` (not its own: a controller does not hear itself), calls
``ups_ecb_tick`` every millisecond, and reads the notes after every call: on
``UPS_ECB_NOTE_STATE`` it writes the blob to ``state_path`` (a temporary file, fsync, rename)
before it sends the frames queued since, as firmware writes its flash. At start the blob is
given back with ``ups_ecb_restore``; a refused one is logged and kept aside as ``.bad``.

The loop calls the library through a ``Backend`` (one method a call of ``c/ups_ecb.h``), of
``target``:

- ``host``: the library compiled for this machine, through ctypes (``broker/_cecb_lib.py``,
  builds ``full`` and ``asan``);
- ``m0``: the Cortex-M0+ image a board flashes, in an emulator (``ups/_armecb.py``, builds
  ``full``, the ecb-full image of a bus of 127 nodes, and ``small``). A call that faults there
  (an unaligned access, one outside the image's memory, a write to flash) or runs past its
  budget of instructions raises one of the backend's ``errors``: the CAN-ECB then stops
  (``halted``), as a board would reset, sending and writing nothing more.
"""

from __future__ import annotations

import asyncio
import fcntl
import logging
import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import can

from ups._canlink import CanLink
from ups._cnode import now_ms
from ups._errors import ConfigError

from ._cecb_lib import (
    COUNTERS,
    FRAME_BRS,
    FRAME_ERR,
    FRAME_EXT,
    FRAME_FD,
    FRAME_RTR,
    NOTE_ROLE,
    NOTE_STATE,
    ROLES,
    VARIANTS,
    Config,
    HostEcb,
    load,
)  # fmt: skip
from ._quota import QUOTA

__all__ = [
    "TARGETS", "Backend", "CEcb", "Config", "backend", "prepare", "serve", "write_atomically",
]  # fmt: skip

log = logging.getLogger("ups.c_ecb")

RECOVERY = 2.0  #: seconds after Hello the CAN-ECB listens and adopts (CanEcb's)
LEASE = 86_400.0  #: seconds a TxNode or etag unused may be reclaimed (CanEcb's)
TICK = 0.001  #: seconds between ups_ecb_tick calls
TARGETS = {"host": ("full", "asan"), "m0": ("full", "small")}  #: target -> its builds


class Backend(Protocol):
    """One ``ups_ecb_t`` and the calls of ``c/ups_ecb.h`` on it (``HostEcb``, ``ArmEcb``).
    Configurations are ``ups_ecb_config_t``'s bytes (``Config``), frames (id, flags, data)."""

    name: str  #: what runs, for the log
    config: dict[str, int]  #: the table sizes, by ``CONFIG``'s names

    @property
    def errors(self) -> tuple[type[Exception], ...]:
        """What a call raises when the code stopped (none: it never stops)."""

    def default_config(self) -> bytes: ...
    def init(self, cfg: bytes, instance: int) -> int: ...
    def restore(self, blob: bytes) -> int: ...
    def start(self, now: int) -> None: ...
    def rx(self, now: int, can_id: int, flags: int, data: bytes) -> None: ...
    def tick(self, now: int) -> None: ...
    def notes(self) -> int: ...
    def pop_tx(self) -> tuple[int, int, bytes] | None: ...
    def save(self) -> bytes: ...
    def role(self) -> int: ...
    def counters(self) -> tuple[int, ...]: ...
    def node(self, i: int) -> tuple[int, int]: ...
    def channel(self, i: int) -> tuple[int, int]: ...
    def channel_users(self, i: int) -> tuple[int, int, int]:
        """The i-th channel's etag (-1: an unused entry), and the TxNodes that subscribe to it
        and those that publish on it (bit t: TxNode t)."""


def backend(target: str = "host", variant: str = "full", image: Path | None = None) -> Backend:
    """A fresh ``ups_ecb_t`` of ``variant`` (one of ``TARGETS[target]``) on ``target``; on
    "m0", ``image`` runs that image (linked by ``ups._armnode.build_image``) instead."""
    if variant not in TARGETS.get(target, ()):
        builds = ", ".join(TARGETS.get(target, ())) or "none"
        raise ConfigError(f"the C CAN-ECB's builds on {target!r} are {builds}, not {variant!r}")
    if target == "m0":
        from ups._armecb import arm_ecb

        return arm_ecb(variant, image)
    if image is not None:
        raise ConfigError("an image is for the m0 target")
    return HostEcb(variant)


def prepare(target: str = "host", variant: str = "full", image: Path | None = None) -> None:
    """Build what ``backend(target, variant)`` runs (or say why it cannot be), before a bus is
    opened."""
    if target == "m0":
        from ups._armecb import BUILDS, arm_ecb
        from ups._armnode import build_image

        if image is not None:
            arm_ecb(variant, image)  # loaded once here: a bad image fails before the bus opens
        elif variant in BUILDS:
            build_image(BUILDS[variant])
        return
    if variant in VARIANTS:
        load(variant)


def write_atomically(path: Path, data: bytes) -> None:
    """``data`` in ``path``, whole or not at all: a temporary file beside it, fsync, rename,
    fsync of the folder (so the rename is durable too)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


class CEcb:
    """libups-ecb serving the bus of ``link``, its durable state in ``state_path``, on
    ``target`` ("host" or "m0") built as ``variant`` (on "m0", ``image``: an image of
    ``ups._armnode.build_image``'s instead).

    ``max_channels`` None: the library's default (its table's size). ``on_sent(can_id, data)``,
    when set, is called with every frame sent (after the blob was written, if it had to be).
    ``on_halt``, when set, is called once if the code stops (``halted`` says why).
    """

    def __init__(
        self,
        link: CanLink,
        state_path: str | Path,
        *,
        bitrate: int = 500_000,
        recovery: float = RECOVERY,
        lease: float = LEASE,
        max_channels: int | None = None,
        quota: tuple[int, int, int, int, int] = QUOTA,
        variant: str = "full",
        target: str = "host",
        image: Path | None = None,
    ) -> None:
        self.link = link
        self.state_path = Path(state_path)
        self.variant = variant
        self._c = backend(target, variant, image)
        self.config = dict(self._c.config)
        self._handler = self._on_frame  # one bound method, so the link can tell it apart
        self.instance = secrets.randbits(64)
        cfg = Config.from_buffer_copy(self._guarded_at_start(self._c.default_config))
        cfg.bitrate = bitrate
        cfg.fd = 1 if link.fd else 0
        cfg.recovery_ms = _ranged("recovery", round(recovery * 1000), 100, 10_000, "ms")
        cfg.lease_s = _ranged("lease", round(lease), 1, 0xFFFFFFFF, "s")
        if max_channels is not None:
            cfg.max_channels = _ranged("max_channels", max_channels, 1, 0xFFFF, "")
        for k, q in enumerate(quota):
            cfg.quota[k] = _ranged("quota", q, 0, 0xFFFF, "")
        if self._guarded_at_start(self._c.init, bytes(cfg), self.instance) < 0:
            raise ConfigError(f"ups_ecb_init refused the configuration (recovery {recovery} s, "
                              f"bitrate {bitrate}, lease {lease} s)")  # fmt: skip
        self.bitrate = bitrate
        self.recovery = recovery
        self.storage_errors = 0
        self.storage_error: str | None = None
        self.restored = False  #: the state file's blob was taken back at start
        self.on_sent: Callable[[int, bytes], None] | None = None
        self.on_halt: Callable[[], None] | None = None
        self.halted: str | None = None  #: why the code stopped (a fault of the image)
        self._saved: bytes | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._started = False
        self._closed = False
        self._role = 0
        self._lock_fd = -1

    def _guarded_at_start(self, call: Callable[..., Any], *args: Any) -> Any:
        """``call(*args)``, a stop of the code a ConfigError (nothing runs yet to stop)."""
        try:
            return call(*args)
        except self._c.errors as exc:
            raise ConfigError(f"the CAN-ECB's code stopped at start: {exc}") from exc

    # --- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        """Take the saved blob back, then listen on the bus and say Hello (ups_ecb_start).
        ConfigError when the state file can be neither read nor written."""
        self._lock()
        self._guarded_at_start(self._restore)
        # an unwritable state file is an error now, not on a join
        self._guarded_at_start(lambda: self._save(initial=True))
        self.link.add_handler(self._handler, None)
        self.link.start()
        self._started = True
        # the tables counted before the Hello: not between it and the frames that follow
        tables = len(self.txnodes), len(self.etags)
        self._step(self._c.start, now_ms())
        if self.halted is not None:
            return
        self._timer = asyncio.get_running_loop().call_later(TICK, self._tick)
        log.info(
            "CAN-ECB on %s (%s, in C): %d TxNodes, %d etags bound (%s), instance %016x",
            self.link.channel_info, self._c.name, *tables, self.state_path, self.instance,
        )  # fmt: skip

    def close(self) -> None:
        """Stop serving the bus (the link stays open) and write the blob (not after the code
        stopped: the file keeps the last blob written, as a board's flash). Safe to call
        twice."""
        if self._closed:
            return
        self._closed = True
        self._stop_serving()
        if self._started and self.halted is None:
            self._save()
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1

    def _stop_serving(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.link.remove_handler(self._handler)

    def _lock(self) -> None:
        """Hold ``STATE.lock`` (one CAN-ECB per state file), or fail naming the file."""
        path = self.state_path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(f"{path}.lock", os.O_RDONLY | os.O_CREAT, 0o644)
        except OSError as exc:
            raise ConfigError(f"cannot use the state file {path}: {exc.strerror or exc}") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise ConfigError(f"the state file {path} is in use by another CAN-ECB") from None
        self._lock_fd = fd

    def _restore(self) -> None:
        path = self.state_path
        try:
            blob = path.read_bytes()
        except FileNotFoundError:
            return
        except OSError as exc:
            raise ConfigError(f"cannot read the state file {path}: {exc.strerror}") from exc
        if self._c.restore(blob) >= 0:
            self.restored = True
            self._saved = blob
            return
        bad = path.with_name(path.name + ".bad")
        try:
            os.replace(path, bad)
        except OSError as exc:
            raise ConfigError(f"cannot move the refused state file {path} aside: {exc}") from exc
        log.error("the state file %s was refused (corrupt, truncated or of other tables): kept "
                  "as %s; the CAN-ECB relearns the bus from the nodes", path, bad)  # fmt: skip

    def _save(self, *, initial: bool = False) -> bool:
        """Write the blob if it changed; False (counted, logged) when the write failed."""
        blob = self.blob()
        if not blob:
            error = f"ups_ecb_save wrote nothing (into {self.config['blob_max']} bytes)"
        elif blob == self._saved and not initial:
            return True
        else:
            try:
                write_atomically(self.state_path, blob)
            except OSError as exc:
                if initial:
                    raise ConfigError(
                        f"cannot write the state file {self.state_path}: {exc.strerror or exc}"
                    ) from exc
                error = f"{exc.strerror or exc}"
            else:
                self._saved = blob
                self.storage_error = None
                return True
        self.storage_errors += 1
        self.storage_error = error
        log.error("C CAN-ECB could not write its state to %s: %s", self.state_path, error)
        return False

    # --- the loop --------------------------------------------------------------------------

    def _tick(self) -> None:
        self._timer = asyncio.get_running_loop().call_later(TICK, self._tick)
        self._step(self._c.tick, now_ms())

    def _on_frame(self, msg: can.Message) -> None:
        data = bytes(msg.data)[: self.config["mtu"]]  # a controller of this MTU keeps no more
        flags = (
            (FRAME_EXT if msg.is_extended_id else 0)
            | (FRAME_FD if msg.is_fd else 0)
            | (FRAME_BRS if msg.bitrate_switch else 0)
            | (FRAME_RTR if msg.is_remote_frame else 0)
            | (FRAME_ERR if msg.is_error_frame else 0)
        )
        self._step(self._c.rx, now_ms(), msg.arbitration_id & 0x1FFFFFFF, flags, data)

    def _step(self, call: Callable[..., None], *args: Any) -> None:
        """One call of the library, then what it left to do; a stop of the code halts the
        CAN-ECB."""
        if self.halted is not None:
            return
        try:
            call(*args)
            self._after()
        except self._c.errors as exc:
            self._halt(str(exc))

    def _halt(self, why: str) -> None:
        """The code stopped (as a board's would, to reset): nothing more is sent or written."""
        self.halted = why
        self._stop_serving()
        log.error("the CAN-ECB's code stopped (%s): %s", self._c.name, why)
        if self.on_halt is not None:
            self.on_halt()

    def _after(self) -> None:
        """What a call left to do: the blob first (on NOTE_STATE), then the frames."""
        notes = self._c.notes()
        if notes & NOTE_ROLE:
            self._role_changed()
        durable = not notes & NOTE_STATE or self._save()
        while (frame := self._c.pop_tx()) is not None:
            can_id, flags, data = frame
            if not durable:  # what a reset would forget is not announced: the asker retries
                continue
            self.link.send(can_id, data, self._handler, fd=bool(flags & FRAME_FD))
            if self.on_sent is not None:
                self.on_sent(can_id, data)

    def _role_changed(self) -> None:
        role = self._c.role()
        before, self._role = self._role, role
        if ROLES[role] == "standby":
            log.error("another CAN-ECB already serves this bus: this CAN-ECB stands by and "
                      "answers nothing")  # fmt: skip
        elif ROLES[before] == "standby":
            log.warning("the CAN-ECB that served went silent or left a request unanswered: "
                        "this one serves the bus again")  # fmt: skip

    # --- tables and statistics -------------------------------------------------------------

    @property
    def role(self) -> str:
        return ROLES[self._c.role()]

    @property
    def standby(self) -> bool:
        """Another CAN-ECB serves the bus."""
        return self.role == "standby"

    @property
    def healthy(self) -> bool:
        """False while writing the state fails or another CAN-ECB serves the bus, and once the
        code stopped."""
        return self.halted is None and self.storage_error is None and not self.standby

    @property
    def txnodes(self) -> dict[int, int]:
        """node id -> TxNode, every assignment of the tables."""
        out: dict[int, int] = {}
        for i in range(self.config["nodes"]):
            txnode, node_id = self._c.node(i)
            if txnode >= 0:
                out[node_id] = txnode
        return out

    @property
    def etags(self) -> dict[int, int]:
        """channel UID -> etag, every binding of the tables."""
        return {uid: etag for _, uid, etag in self._channels()}

    def _channels(self) -> list[tuple[int, int, int]]:
        out = []
        for i in range(self.config["channels"]):
            etag, uid = self._c.channel(i)
            if etag >= 0:
                out.append((i, uid, etag))
        return out

    def blob(self) -> bytes:
        """What ups_ecb_save() writes now (empty: it wrote nothing)."""
        return self._c.save()

    def counters(self) -> dict[str, int]:
        """ups_ecb_counters(), by name."""
        return dict(zip(COUNTERS, self._c.counters(), strict=True))

    def stats(self) -> dict[str, object]:
        return self._stats(len(self.txnodes), len(self.etags))

    def _stats(self, txnodes: int, etags: int) -> dict[str, object]:  # the tables' sizes given
        return {
            **self.counters(),
            "storage_errors": self.storage_errors,
            "txnodes": txnodes,
            "etags": etags,
            "storage_error": self.storage_error,
            "state": str(self.state_path),
            "healthy": self.healthy,
            "standby": self.standby,
            "role": self.role,
            "instance": f"{self.instance:016x}",
        }

    def status(self) -> dict[str, Any]:
        """The tables as ``ups status`` and ``ups ls`` show them (CanEcb.status()'s shape)."""
        txnodes = self.txnodes
        bound = self._channels()
        channels = []
        for i, uid, etag in sorted(bound, key=lambda c: c[2]):
            _, subscribers, publishers = self._c.channel_users(i)  # one call a channel
            channels.append({
                "uid": f"0x{uid:016x}", "etag": f"0x{etag:04x}",
                "publishers": [f"0x{t:02x}" for t in range(0x7F) if publishers >> t & 1],
                "subscribers": [f"0x{t:02x}" for t in range(0x7F) if subscribers >> t & 1],
            })  # fmt: skip
        return {
            "nodes": [{"node_id": f"0x{n:016x}", "txnode": f"0x{t:02x}"}
                      for n, t in sorted(txnodes.items(), key=lambda i: i[1])],
            "channels": channels,
            "stats": self._stats(len(txnodes), len(bound)),
        }  # fmt: skip


def _ranged(name: str, value: int, low: int, high: int, unit: str) -> int:
    if not low <= value <= high:
        raise ConfigError(f"{name} must be {low}..{high}{' ' + unit if unit else ''}: {value}")
    return value


async def serve(
    bus: str, state_path: str | Path, bitrate: int = 500_000, status: str | None = None,
    metrics: str | None = None, **options: Any,
) -> int:  # fmt: skip
    """Run libups-ecb (``options``: ``CEcb``'s, ``target`` and ``variant`` among them) as the
    CAN-ECB of ``bus`` until cancelled or until its code stops (``CanEcb``'s ``serve``: with
    ``status`` (HOST:PORT) its tables served to ``ups status`` and ``ups ls``, with ``metrics``
    its counters to Prometheus). The blob is written when the run ends, unless the code
    stopped. Returns 1 if the code stopped or writing the state file failed during the run,
    else 0."""
    from ._serving import run

    halted = asyncio.Event()

    def make(link: CanLink) -> CEcb:
        ecb = CEcb(link, state_path, bitrate=bitrate, **options)
        ecb.on_halt = halted.set
        return ecb

    running = asyncio.ensure_future(run(bus, make, "c-ecb", status, metrics))
    stopped = asyncio.ensure_future(halted.wait())
    try:
        await asyncio.wait((running, stopped), return_when=asyncio.FIRST_COMPLETED)
    except asyncio.CancelledError:
        pass  # SIGTERM or SIGINT: the orderly end, as run's own
    finally:
        stopped.cancel()
        running.cancel()  # run ends in order (it returns the CAN-ECB) when cancelled
    ecb = await running
    if ecb.storage_errors:
        log.error("the state file %s could not be written %d times", state_path,
                  ecb.storage_errors)  # fmt: skip
    return 1 if ecb.storage_errors or ecb.halted is not None else 0

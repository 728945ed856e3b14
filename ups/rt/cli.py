"""Command line of the CAN response-time analysis: ``ups analyze FILE`` (or ``python -m ups.rt``).

Exit codes: 0 when the analysis ran (whatever it found), 1 when ``--assign audsley`` finds no
schedulable ordering, 2 for bad input (unreadable file, malformed CSV, invalid options).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from collections.abc import Sequence
from fractions import Fraction
from typing import TextIO

from ._analysis import BLOCKINGS, METHODS, Blocking, Method, _prepare, analyze
from ._model import MessageSpec, NotSchedulable, Result, _ms, _ordered, load_csv
from ._priority import audsley, deadline_monotonic, to_priority_field

_PROG = "ups analyze"
_ASSIGN = ("audsley", "deadline-monotonic")


def _bitrate(text: str) -> int:
    """Parse a bit rate: ``250000``, ``250k``, ``1M`` (bit/s)."""
    raw = text.strip().lower().removesuffix("bit/s").removesuffix("bps")
    factor = 1
    if raw.endswith("k"):
        raw, factor = raw[:-1], 1000
    elif raw.endswith("m"):
        raw, factor = raw[:-1], 1_000_000
    try:
        value = Fraction(raw) * factor
    except (ValueError, ZeroDivisionError):
        raise argparse.ArgumentTypeError(f"invalid bit rate {text!r}") from None
    if value <= 0 or value.denominator != 1:
        raise argparse.ArgumentTypeError(f"invalid bit rate {text!r}: need a positive integer")
    return value.numerator


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``analyze`` options to ``parser`` (positional FILE included)."""
    parser.add_argument(
        "file",
        metavar="FILE",
        help="CSV: first column names each message; columns size_bytes, jitter_ms, period_ms, "
        "deadline_ms; optional priority (lower = higher), else rows are highest priority first. "
        "Or a channel catalog (.toml): its channels with a realtime declaration",
    )
    parser.add_argument(
        "--bitrate",
        metavar="BPS",
        type=_bitrate,
        default=500_000,
        help="bus bit rate in bit/s, e.g. 250000 or 250k (default: 500k)",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="davis2007",
        help="davis2007: revised analysis with queuing jitter (default); tindell1994: the "
        "computation behind Table 1 of paper 000 (own queuing jitter left out; optimistic)",
    )
    parser.add_argument(
        "--id-bits", type=int, choices=(11, 29), default=29, help="identifier length (default 29)"
    )
    parser.add_argument(
        "--blocking",
        choices=BLOCKINGS,
        default="max-frame",
        help="max-frame: any longest frame may block, foreign traffic included (default); "
        "lower-priority: only the set's lower-priority frames",
    )
    parser.add_argument("--fd", action="store_true", help="CAN FD frames (davis2007 only)")
    parser.add_argument(
        "--assign",
        choices=_ASSIGN,
        help="assign priorities (mapped onto the 8-bit priority field) instead of using the file's",
    )
    parser.add_argument(
        "--node-cycles",
        metavar="SEND[,RECEIVE]",
        type=_node_cycles,
        default=None,
        help="the nodes' own work, in CPU cycles (c/README.md, 'Cycles on Cortex-M0+': SEND = "
        "ups_publish + ups_tx_peek + ups_tx_pop, RECEIVE = ups_rx of the node's configuration): "
        "SEND is added to every message's queuing jitter, RECEIVE to its response time, "
        "which the deadline then bounds",
    )
    parser.add_argument(
        "--node-mhz",
        metavar="MHZ",
        type=_positive_fraction,
        default=Fraction(48),
        help="the nodes' CPU clock for --node-cycles (default: 48)",
    )
    parser.add_argument("--json", action="store_true", help="print a JSON object")


def _positive_fraction(text: str) -> Fraction:
    try:
        value = Fraction(text)
    except (ValueError, ZeroDivisionError):
        raise argparse.ArgumentTypeError(f"expected a number, not {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, not {text!r}")
    return value


def _node_cycles(text: str) -> tuple[int, int]:
    """``SEND`` or ``SEND,RECEIVE``: cycles (non-negative integers)."""
    parts = text.split(",")
    try:
        values = [int(part) for part in parts]
    except ValueError:
        values = []
    if len(parts) > 2 or not values or min(values) < 0:
        raise argparse.ArgumentTypeError(
            f"expected SEND or SEND,RECEIVE cycles (integers >= 0), not {text!r}"
        )
    return values[0], values[1] if len(values) == 2 else 0


def _with_nodes(
    specs: list[MessageSpec], send_ms: Fraction, receive_ms: Fraction
) -> list[MessageSpec]:
    """The set the bus sees when every sender takes ``send_ms`` to queue a frame (its queuing
    jitter grows by it) and every receiver ``receive_ms`` to take it (the deadline left for the
    bus shrinks by it)."""
    out = []
    for spec in specs:
        if spec.deadline_ms <= receive_ms:
            raise ValueError(
                f"{spec.name}: its deadline ({_ms(spec.deadline_ms)} ms) leaves the bus no time "
                f"after the receiving node's work ({_ms(receive_ms)} ms)"
            )
        out.append(dataclasses.replace(
            spec, jitter_ms=spec.jitter_ms + send_ms, deadline_ms=spec.deadline_ms - receive_ms
        ))  # fmt: skip
    return out


def _load_catalog(path: str) -> list[MessageSpec]:
    """The real-time channels of a UPS channel catalog (their ``realtime`` declarations)."""
    from .._catalog import Catalog
    from .._errors import ConfigError

    try:
        catalog = Catalog.load(path)
    except ConfigError as error:
        raise ValueError(str(error)) from None
    specs = []
    for spec in catalog:
        if spec.realtime is None:
            continue
        name = spec.name or f"0x{spec.uid:016x}"
        if spec.size is None or not spec.fields:
            raise ValueError(f"{path}: {name} is real-time but its payload has no fixed size")
        rt = spec.realtime
        specs.append(
            MessageSpec(
                name,
                spec.size,
                _ms_of(rt.period),
                _ms_of(rt.deadline),
                _ms_of(rt.jitter),
                spec.priority,
            )
        )
    if not specs:
        raise ValueError(f"{path}: no channel has a realtime declaration")
    return specs


def _ms_of(seconds: float) -> Fraction:
    """Seconds as written in the catalog, in exact milliseconds (0.00104 s is 1.04 ms, not
    the 1.0399999999999998 of a float product)."""
    return Fraction(repr(seconds)) * 1000


def _end_to_end(result: Result, receive_ms: Fraction) -> Result:
    response = result.response_time_ms
    if response is None:
        return dataclasses.replace(result, deadline_ms=result.deadline_ms + receive_ms)
    response += receive_ms
    deadline = result.deadline_ms + receive_ms
    return Result(result.name, response, deadline, response <= deadline)


def _error(message: str, stream: TextIO) -> int:
    print(f"{_PROG}: error: {' '.join(message.split())}", file=stream)
    return 2


def run(args: argparse.Namespace) -> int:
    """Run the analysis described by ``args`` (from ``add_arguments``); return the exit code."""
    out, err = sys.stdout, sys.stderr
    method: Method = args.method
    blocking: Blocking = args.blocking
    try:
        specs = _load_catalog(args.file) if args.file.endswith(".toml") else load_csv(args.file)
    except OSError as error:
        reason = error.strerror or str(error)
        return _error(f"cannot read {args.file}: {reason}", err)
    except (ValueError, UnicodeDecodeError) as error:
        return _error(str(error), err)
    priorities: dict[str, int] | None = None
    send_ms = receive_ms = Fraction(0)
    written = specs
    try:
        if args.node_cycles is not None:
            send, receive = args.node_cycles
            send_ms, receive_ms = (Fraction(c) / (args.node_mhz * 1000) for c in (send, receive))
            specs = _with_nodes(specs, send_ms, receive_ms)
        if args.assign:
            if args.assign == "audsley":
                ordering = audsley(
                    specs,
                    args.bitrate,
                    args.id_bits,
                    method=method,
                    blocking=blocking,
                    fd=args.fd,
                )
            else:
                ordering = deadline_monotonic(specs)
            priorities = to_priority_field(ordering)
            specs = [dataclasses.replace(s, priority=priorities[s.name]) for s in specs]
        results = analyze(specs, args.bitrate, method, args.id_bits, blocking=blocking, fd=args.fd)
        _, msgs = _prepare(specs, args.bitrate, method, args.id_bits, blocking, args.fd)
    except NotSchedulable as error:
        print(f"{_PROG}: {error}", file=err)
        return 1
    except ValueError as error:
        return _error(str(error), err)
    if args.node_cycles is not None:  # back to the messages as written, end to end
        results = [_end_to_end(r, receive_ms) for r in results]
        specs = [
            dataclasses.replace(w, priority=s.priority) for w, s in zip(written, specs, strict=True)
        ]
    frame_ms = {msg.spec.name: msg.c for msg in msgs}
    if priorities is None:
        priorities = {
            spec.name: rank if spec.priority is None else spec.priority
            for rank, spec in enumerate(_ordered(specs))
        }
    utilisation = sum((msg.c / msg.t for msg in msgs), Fraction(0))
    header = {
        "file": str(args.file),
        "method": method,
        "bitrate": args.bitrate,
        "id_bits": args.id_bits,
        "blocking": blocking,
        "fd": bool(args.fd),
        "utilisation": float(utilisation),
        "node_send_ms": float(send_ms),
        "node_receive_ms": float(receive_ms),
        "schedulable": all(result.schedulable for result in results),
    }
    try:
        if args.json:
            _print_json(header, specs, results, frame_ms, priorities, out)
        else:
            _print_table(header, specs, results, frame_ms, priorities, out)
        out.flush()
    except BrokenPipeError:  # e.g. piped into head: not an error of the analysis
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, out.fileno())
    return 0


def _print_json(
    header: dict[str, object],
    specs: Sequence[MessageSpec],
    results: Sequence[Result],
    frame_ms: dict[str, Fraction],
    priorities: dict[str, int],
    out: TextIO,
) -> None:
    messages = [
        {
            "name": result.name,
            "priority": priorities[result.name],
            "transmission_time_ms": float(frame_ms[result.name]),
            "response_time_ms": (
                None if result.response_time_ms is None else float(result.response_time_ms)
            ),
            "deadline_ms": float(result.deadline_ms),
            "schedulable": result.schedulable,
        }
        for result in results
    ]
    json.dump({**header, "messages": messages}, out, indent=2)
    out.write("\n")


def _print_table(
    header: dict[str, object],
    specs: Sequence[MessageSpec],
    results: Sequence[Result],
    frame_ms: dict[str, Fraction],
    priorities: dict[str, int],
    out: TextIO,
) -> None:
    utilisation = header["utilisation"]
    assert isinstance(utilisation, float)
    out.write(
        f"{header['method']} analysis of {header['file']}: {header['bitrate']} bit/s, "
        f"{header['id_bits']}-bit identifiers{', CAN FD' if header['fd'] else ''}, "
        f"blocking {header['blocking']}, bus utilisation {utilisation:.1%}\n"
    )
    send, receive = header["node_send_ms"], header["node_receive_ms"]
    if send or receive:
        out.write(
            f"the nodes' own work: {float(send) * 1000:.1f} us to send (in J), "  # type: ignore[arg-type]
            f"{float(receive) * 1000:.1f} us to receive (in R)\n"  # type: ignore[arg-type]
        )
    columns = ("message", "prio", "bytes", "C ms", "J ms", "T ms", "D ms", "R ms", "")
    rows = [
        (
            spec.name,
            str(priorities[spec.name]),
            str(spec.size_bytes),
            _ms(frame_ms[spec.name]),
            _ms(spec.jitter_ms),
            _ms(spec.period_ms),
            _ms(spec.deadline_ms),
            "unbounded" if result.response_time_ms is None else _ms(result.response_time_ms),
            "ok" if result.schedulable else "MISS",
        )
        for spec, result in zip(specs, results, strict=True)
    ]
    widths = [max(len(row[i]) for row in (columns, *rows)) for i in range(len(columns))]
    for row in (columns, *rows):
        cells = [row[0].ljust(widths[0])] + [
            cell.rjust(width) for cell, width in zip(row[1:-1], widths[1:-1], strict=True)
        ]
        out.write(("  ".join(cells) + "  " + row[-1]).rstrip() + "\n")
    missing = [result.name for result in results if not result.schedulable]
    if missing:
        out.write(
            f"{len(missing)} of {len(results)} messages miss their deadlines: "
            f"{', '.join(missing)}\n"
        )
    else:
        out.write(f"all {len(results)} messages meet their deadlines\n")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m ups.rt.cli FILE ...``."""
    parser = argparse.ArgumentParser(
        prog=_PROG, description="Worst-case response-time analysis of a CAN message set."
    )
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

"""``ups c-ecb``: libups-ecb, the CAN-ECB in C (c/ups_ecb.h), run as the CAN-ECB of any
python-can bus, as a microcontroller would run it (``ups.broker.c_ecb``): compiled for this
machine, or its Cortex-M0+ image in an emulator (``--target m0``). Arguments here (cheap
to build), the work in ``ups.broker.c_ecb.serve``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from ups._cliargs import add_can

from ._argparsing import add_ecb_service


def _recovery_arg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, not {text!r}") from None
    if not 0.1 <= value <= 10.0:  # ups_ecb_config_t's recovery_ms: 100..10000
        raise argparse.ArgumentTypeError(f"the recovery window is 0.1 to 10 s, not {text}")
    return value


def add_commands(command: Callable[..., argparse.ArgumentParser]) -> None:
    cmd = command(
        "c-ecb",
        help="run the C CAN-ECB (c/, libups-ecb) as the CAN-ECB of one bus: compiled for "
        "this machine, or the Cortex-M0+ image a board flashes in an emulator (--target m0)",
    )
    add_can(cmd)
    cmd.add_argument(
        "--state", default=None, metavar="FILE",
        help="the file of its durable state (TxNodes, etags: the blob ups_ecb_save writes; "
        "default: the bus's own file beside can-broker's database, ending in .c-ecb)",
    )  # fmt: skip
    cmd.add_argument(
        "--recovery", type=_recovery_arg, default=2.0, metavar="S",
        help="seconds after start spent relearning the bus before answering, 0.1 to 10 "
        "(default 2)",
    )  # fmt: skip
    cmd.add_argument(
        "--target", choices=("host", "m0"), default="host",
        help="host: the library compiled for this machine; m0: the Cortex-M0+ image a board "
        "flashes (make -C c size's), run in an emulator (needs the emu extra: unicorn, and "
        "arm-none-eabi-gcc): a fault of the image (an unaligned access, one outside its "
        "memory) or a call past its instruction budget stops it with exit code 1",
    )  # fmt: skip
    cmd.add_argument(
        "--build", choices=("full", "small", "asan"), default="full",
        help="the library's configuration: full (host: 127 nodes, 2048 channels; m0: the "
        "ecb-full image, 127 nodes, 512 channels), small (m0 only: the ecb-small image, 16 "
        "nodes, 64 channels) or asan (host only: small tables, AddressSanitizer and "
        "UndefinedBehaviorSanitizer: run with LD_PRELOAD=$(cc -print-file-name=libasan.so))",
    )  # fmt: skip
    cmd.add_argument(
        "--image", default=None, metavar="ELF",
        help="with --target m0: run this image instead of --build's (one linked as make -C c "
        "size links, by ups._armnode.build_image, with its state.o and config.h beside it: "
        "a configuration or a test build of your own)",
    )  # fmt: skip
    add_ecb_service(cmd)
    cmd.set_defaults(run=_run_c_ecb)


def default_state(bus: str) -> str:
    """The state file of bus ``bus``: can-broker's database's name, ending in ``.c-ecb``."""
    from ups.broker._store import default_db

    return str(default_db(bus).with_suffix(".c-ecb"))


def _run_c_ecb(args: argparse.Namespace) -> int:
    from ups._cliargs import run_until_signal, warn_if_virtual
    from ups._metrics import check_metrics
    from ups.broker.c_ecb import TARGETS, prepare, serve

    if args.build not in TARGETS[args.target]:
        print(f"ups c-ecb: --target {args.target} runs --build "
              f"{' or '.join(TARGETS[args.target])}", file=sys.stderr)  # fmt: skip
        return 2
    image = None if args.image is None else Path(args.image)
    if image is not None and args.target != "m0":
        print("ups c-ecb: --image is for --target m0", file=sys.stderr)
        return 2
    state = args.state if args.state is not None else default_state(args.can)
    check_metrics(args.metrics)  # before anything starts, or says anything
    prepare(args.target, args.build, image)  # built (or its error said) before the bus opens
    warn_if_virtual(args.can)

    async def run() -> int:
        return await serve(
            args.can, state, args.bitrate, status=args.status, metrics=args.metrics,
            recovery=args.recovery, variant=args.build, target=args.target, image=image,
        )  # fmt: skip

    return run_until_signal(run())

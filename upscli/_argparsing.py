"""The parts of the ``ups`` command line that are about parsing itself: ``--version`` looked up
only when asked, the stand-in for the parsers of commands not being run, ``--metrics`` built only
for the command being run, and the usage and the option meant when an argument is not
recognized."""

from __future__ import annotations

import argparse
from typing import Any


def unrecognized(
    parser: argparse.ArgumentParser, args: argparse.Namespace, unknown: list[str]
) -> None:
    """Exit with the usage of the (sub)command that was given ``unknown`` arguments, and the
    option a misspelt one most likely meant."""
    while True:  # down to the deepest subcommand chosen: its usage is the one to show
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        chosen = getattr(args, sub.dest, None) if sub is not None else None
        if sub is None or chosen not in sub.choices:
            break
        parser = sub.choices[chosen]
    import difflib  # only for a mistake

    message = f"unrecognized arguments: {' '.join(unknown)}"
    options = [o for a in parser._actions for o in a.option_strings if o.startswith("--")]
    meant = difflib.get_close_matches(unknown[0].split("=", 1)[0], options, n=1, cutoff=0.8)
    if unknown[0].startswith("--") and meant:
        message += f" (did you mean {meant[0]}?)"
    parser.error(message)


class Version(argparse.Action):
    """``--version``, looked up only when asked for (importlib.metadata is not cheap)."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, help="print the version and exit")

    def __call__(self, parser: argparse.ArgumentParser, *args: Any) -> None:
        from importlib.metadata import PackageNotFoundError, version

        try:
            text = version("ups-pubsub")
        except PackageNotFoundError:
            text = "(not installed)"
        print(f"ups {text}")
        parser.exit()


class Unbuilt:
    """Stands in for the parser of a command that is not being run: whatever is asked of it
    (arguments, groups, subcommands, defaults) is not built, so ``ups --help`` and every
    command pay only for their own options."""

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: self


def add_metrics(cmd: argparse.ArgumentParser) -> None:
    """A daemon's ``--metrics`` option, when its parser is built (``ups._metrics`` loads
    ``logging``, which ``ups --help`` and the other commands' parsers do without)."""
    if not isinstance(cmd, Unbuilt):
        from ups._metrics import add_metrics as add

        add(cmd)


def add_ecb_service(cmd: argparse.ArgumentParser) -> None:
    """What both CAN-ECB daemons (``ups can-broker``, ``ups c-ecb``) take besides their own
    options: the bus's bit rate, the status port and the metrics."""
    from ups._cliargs import positive_int

    cmd.add_argument(
        "--bitrate", type=positive_int, default=500_000,
        help="the bus's bit rate, for admitting real-time channels (default 500000)",
    )  # fmt: skip
    cmd.add_argument(
        "--status", metavar="HOST:PORT", default=None,
        help="also serve the tables (nodes, etags, who publishes and subscribes) there, for "
        "'ups status' and 'ups ls --can BUS --ecb HOST:PORT' (default: not served)",
    )  # fmt: skip
    add_metrics(cmd)

"""What each entry point loads: ``ups --help`` and TCP/IP-only programs stay light.

Structural, not timed: a fresh interpreter reports which heavy modules got imported.
"""

from __future__ import annotations

import subprocess
import sys

from .procs import ROOT

HEAVY = ("can", "msgpack", "asyncio", "cryptography", "ups.rt._analysis", "prometheus_client")
#: what ``ups --help`` did import before it knew no command runs (issue 43): the metrics (and
#: with them logging), every tool's module (the console's web guard), JSON, difflib
UNCHOSEN = ("ups._metrics", "logging", "ups.tools.console", "ups.tools.ls", "json", "difflib")


def loaded_after(code: str, heavy: tuple[str, ...] = HEAVY) -> set[str]:
    probe = f"{code}\nimport sys\nprint(' '.join(m for m in {heavy!r} if m in sys.modules))"
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=60,
        check=True,
    )  # fmt: skip
    return set(done.stdout.split())


def test_ups_help_loads_nothing_heavy() -> None:
    code = "import contextlib, io\nimport upscli\nwith contextlib.suppress(SystemExit), "
    code += "contextlib.redirect_stdout(io.StringIO()):\n    upscli.main(['--help'])"
    assert loaded_after(code) == set()


def test_ups_help_imports_nothing_a_command_needs_only_when_it_runs() -> None:
    code = "import contextlib, io\nimport upscli\nwith contextlib.suppress(SystemExit), "
    code += "contextlib.redirect_stdout(io.StringIO()):\n    upscli.main(['--help'])"
    assert loaded_after(code, UNCHOSEN) == set()
    code = code.replace("['--help']", "['pub', '--help']")  # a command's own, not the others'
    assert loaded_after(code, UNCHOSEN) == set()


def test_a_daemons_help_loads_nothing_heavy() -> None:
    """``--metrics`` is offered by every daemon; prometheus-client loads only to serve."""
    for daemon in ("broker", "can-broker", "gateway", "jaus", "console"):
        code = "import contextlib, io\nimport upscli\nwith contextlib.suppress(SystemExit), "
        code += (
            f"contextlib.redirect_stdout(io.StringIO()):\n    upscli.main([{daemon!r}, '--help'])"
        )
        assert loaded_after(code) == set(), daemon


def test_importing_ups_loads_nothing_heavy() -> None:
    assert loaded_after("import ups\nfrom ups import ConfigError, name_to_uid") == set()


def test_a_tcp_node_does_not_load_python_can() -> None:
    code = "import asyncio, ups\n"
    code += "async def main():\n"
    code += "    node = ups.Node(broker='127.0.0.1:1', join_timeout=0.01)\n"
    code += "    try:\n        await node.start()\n"
    code += "    except ups.BrokerUnavailable:\n        pass\n"
    code += "asyncio.run(main())"
    assert "can" not in loaded_after(code)

"""The operators' tools behind ``ups ls``, ``record``, ``decode``, ``replay``, ``dbc``,
``monitor`` and ``console``: one module per command, each with ``HELP``,
``add_arguments(parser)`` and ``run(args) -> exit code``.

The command line lists the tools from ``COMMANDS`` (each one's help line: a test holds it
equal to the tool's ``HELP``) and imports a tool's module only when that tool is the command:
``ups --help`` stays quick. A module imports only the standard library and
light ``ups`` modules at its top; what it needs beyond (python-can, rich, aiohttp, cantools)
it imports in ``run``.
"""

#: each tool's command and its line in ``ups --help``
COMMANDS = {
    "ls": "list the nodes and channels of a network",
    "monitor": "a live view of a network: channels, rates, last values, nodes, drops, bus load",
    "record": "record a network's events to a python-can log file (.asc, .blf, .log)",
    "decode": "print a recording or a candump/python-can log of a UPS bus in UPS terms",
    "replay": "publish a recording's events again on a live network, by channel UID",
    "dbc": "write a DBC that labels a UPS bus's frames (for cantools, SavvyCAN ...)",
    "console": "a web page of the live network: channels, nodes, a plot, a form to publish",
}

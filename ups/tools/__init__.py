"""The operators' tools behind ``ups ls``, ``record``, ``decode``, ``replay``, ``dbc``,
``monitor`` and ``console``: one module per command, each with ``HELP``,
``add_arguments(parser)`` and ``run(args) -> exit code``.

The command line lists the tools from its own table of their help lines (``upscli.TOOLS``, a
test holds each equal to the tool's ``HELP``) and imports a tool's module only when that tool
is the command: ``ups --help`` stays quick. A module imports only the standard library and
light ``ups`` modules at its top; what it needs beyond (python-can, rich, aiohttp, cantools)
it imports in ``run``.
"""

COMMANDS = ("ls", "monitor", "record", "decode", "replay", "dbc", "console")

"""The operators' tools behind ``ups ls``, ``record``, ``decode``, ``replay``, ``dbc``,
``monitor`` and ``console``: one module per command, each with ``HELP``,
``add_arguments(parser)`` and ``run(args) -> exit code``.

A command module imports only the standard library and light ``ups`` modules at its top: the
whole command line is built from them on every ``ups`` call, and ``ups --help`` stays quick.
What a command needs beyond that (python-can, rich, aiohttp, cantools) it imports in ``run``.
"""

COMMANDS = ("ls", "monitor", "record", "decode", "replay", "dbc", "console")

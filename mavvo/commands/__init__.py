"""One module per ``mavvo`` command, each with ``add_parser(subparsers)`` and ``main(args) -> int``.

The top layer: may import every layer of mavvo, and ``sim`` inside the functions of the commands
that need it (sim, replay, and the ``sim:`` camera of run), never at module level."""

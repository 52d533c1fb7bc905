"""One module per ``mls`` command or command group (``<name>_cmd.py``), assembled by
:mod:`cli.app`."""

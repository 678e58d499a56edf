"""CLI sub-commands, one module each (see :mod:`handfe.cli`)."""

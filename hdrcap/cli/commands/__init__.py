"""One module per ``hdrcap`` command; each defines a click command named ``command``.

:mod:`hdrcap.cli` discovers the modules of this package, so a new command is a new file.
"""

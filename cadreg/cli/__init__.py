"""The `cadreg` command line: one entry point, sub-commands in `*_cmd.py` modules and in plugins."""

"""The command line's commands: one module each (add_parser, run); options.py is shared."""

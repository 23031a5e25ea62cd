"""One module per ``gmmgp`` subcommand: ``add_parser(subparsers)`` and ``run(args)``."""

"""Subcommands of ``dmlo``: one module each, with ``register(subparsers)``."""

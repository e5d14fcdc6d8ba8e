"""The runtime's subcommands, each a ``Command`` registered under ``dimenet.commands``."""

"""Subcommands of the `dimenet` command line that live in the runtime."""

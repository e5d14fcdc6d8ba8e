"""The ``dimenet`` command line: the parser core (main), argument types, progress, commands/."""

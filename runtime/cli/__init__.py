"""The ``dimenet`` command line: the parser core (main), argument types (arguments), the camera argument, commands/."""

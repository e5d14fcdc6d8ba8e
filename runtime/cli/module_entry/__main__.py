"""`python -m dimenet`: the `dimenet` command. pyproject.toml installs this folder as the ``dimenet``
namespace package's portion (it has no ``__init__.py``, so dimenet.runtime, dimenet.training and
dimenet.export stay their own packages)."""

import sys

from dimenet.runtime.cli.main import main

if __name__ == "__main__":  # imported (a walk of the packages), it runs nothing
    sys.exit(main())

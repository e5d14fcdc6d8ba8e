"""Fixtures of the CLI's tests."""

from __future__ import annotations

import pytest

from dimenet.runtime.cli import extras


@pytest.fixture
def every_extra_present(monkeypatch):
    """The CLI's extras check (cli/extras.py) finds every extra's modules, so that a command's own argument
    checks, which come before its imports, are what answers, on the base install as on a full one."""
    monkeypatch.setattr(extras, "_absent", lambda module: False)

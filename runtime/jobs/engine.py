"""Many jobs at once: one function over a list of items, here one after another, or as Ray tasks
(the `fleet` extra) on a cluster; each item's outcome in the items' order.

``--address`` (``cli.arguments.add_address_argument``) names the engine: absent, the jobs run in
this process in order (as every command always did); ``local`` or ``local:N`` starts a Ray cluster
on this machine with N CPUs (default: all); ``auto`` or ``ray://host:port`` joins a running one. Ray
is imported only then, so the runtime and the other extras never need it. A job's exception is its
outcome, not the run's: the others finish and the caller reports it by name.
"""

from __future__ import annotations

import logging
import os
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Optional

from dimenet.runtime.errors import DimenetError
from dimenet.runtime.jobs.progress import progress

# The logger of Ray's token-authentication notices (ray/_private/authentication/authentication_token_setup.py).
RAY_TOKEN_LOGGER = "ray._private.authentication.authentication_token_setup"


class EngineError(DimenetError):
    """The engine cannot run the jobs: the address is unusable."""


@dataclass(frozen=True)
class Outcome:
    """One job: its value, or the one-line error it ended with (value None); seconds of wall time."""

    value: Any
    error: Optional[str]
    seconds: float


def _run_one(function: Callable, item) -> Outcome:
    start = time.monotonic()
    try:
        return Outcome(function(item), None, time.monotonic() - start)
    except DimenetError as exc:  # a typed error names its own problem
        return Outcome(None, str(exc), time.monotonic() - start)
    except Exception as exc:  # anything else: its type and last frame, on one line
        where = traceback.format_exc(limit=-1).strip().splitlines()[-1]
        return Outcome(None, f"{type(exc).__name__}: {exc} ({where})", time.monotonic() - start)


class Engine:
    """The engine of ``address`` (see the module docstring) for one or more batches of jobs: a
    context manager holding one Ray session (started on entry, shut down on exit) across its
    ``run_all`` calls, so a command with dependent batches pays Ray's start-up once."""

    def __init__(self, address: Optional[str] = None) -> None:
        self.address, self._ray = address, None

    def __enter__(self) -> Engine:
        if self.address is not None:
            self._ray = _ray(self.address)
        return self

    def __exit__(self, *exc) -> None:
        if self._ray is not None:
            self._ray.shutdown()
            self._ray = None

    def run_all(self, function: Callable, items: list, *, cpus_per_job: int = 1, desc: str = "") -> list:
        """``function(item)`` for every item as an Outcome, in the items' order: in this process
        without an address, else as Ray tasks of ``cpus_per_job`` CPUs each (``function`` and the
        items must be importable or plain data, as Ray ships them to its workers)."""
        if self._ray is None:
            return [_run_one(function, item) for item in progress(items, desc=desc)]
        task = self._ray.remote(num_cpus=cpus_per_job)(_run_one)
        pending = [task.remote(function, item) for item in items]
        return [self._ray.get(p) for p in progress(pending, desc=desc)]


def run_all(
    function: Callable, items: list, *, address: Optional[str] = None, cpus_per_job: int = 1, desc: str = ""
) -> list:
    """One batch on the engine of ``address``: ``Engine(address).run_all`` in its own session."""
    with Engine(address) as engine:
        return engine.run_all(function, items, cpus_per_job=cpus_per_job, desc=desc)


def _quiet_token_banner(record: logging.LogRecord) -> bool:
    """False for Ray's notice that token authentication is on (its default for a cluster it starts), which
    it logs on every `--address local` run; its other warnings pass."""
    return not record.getMessage().startswith("Token authentication is enabled for this Ray cluster")


def _ray(address: str):
    """Ray, initialised for ``address`` (see the module docstring). Without Ray, an ImportError: the
    command line names the fleet extra before any job runs (cli/extras.py)."""
    import ray

    logging.getLogger(RAY_TOKEN_LOGGER).addFilter(_quiet_token_banner)
    kwargs: dict = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
    if address == "local" or address.startswith("local:"):
        cpus = address.partition(":")[2]
        if cpus and not (cpus.isdigit() and int(cpus) >= 1):
            raise EngineError(f"--address {address}: local:N needs N >= 1 CPUs")
        kwargs["num_cpus"] = int(cpus) if cpus else os.cpu_count()
    else:
        kwargs["address"] = address
    try:
        ray.init(**kwargs)
    except Exception as exc:  # Ray's own errors (no cluster at the address, ...)
        raise EngineError(
            f"--address {address}: Ray could not start or join a cluster ({type(exc).__name__}: {exc})"
        ) from None
    return ray

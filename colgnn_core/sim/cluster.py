"""A Dask ``distributed`` cluster for the ground-truth solver: ``colgnn generate --dask ADDRESS`` (and ``fit``).

``ADDRESS`` is the scheduler of the user's cluster (``tcp://10.0.0.5:8786``: started with ``dask scheduler`` and
``dask worker tcp://10.0.0.5:8786 --nthreads 1`` on each machine, or by dask-jobqueue / dask-kubernetes), or
``local:N`` for a cluster of N single-threaded worker processes on this machine (trying it out, the tests).

Each sequence is one task: the scene travels to the workers once (``scatter``), a task returns the simulated
sequence and this process writes it and the manifest, so the workers need colgnn installed (the same version)
but no shared file system and no scene files. Dask is imported only here and only when asked for: it is light
(pure Python) but slow to import.
"""

from __future__ import annotations

import contextlib
import re
from typing import Iterator

from colgnn_core.errors import InputError

LOCAL_RE = re.compile(r"^local:(\d+)$")
ADDRESS_RE = re.compile(r"^(tcp|tls|ucx|inproc)://\S+$|^[\w.\-]+:\d+$")
CONNECT_TIMEOUT_S = 20


def check_workers(jobs: int, dask: str | None) -> None:
    """InputError unless ``jobs`` >= 1 and at most one of local processes (jobs > 1) and a Dask cluster is asked."""
    if int(jobs) < 1:
        raise InputError(f"jobs must be >= 1, got {jobs}")
    if dask is not None:
        check_address(dask)
        if int(jobs) > 1:
            raise InputError("give either --jobs (local processes) or --dask (a cluster), not both")


def check_address(address: str) -> str:
    """``local:N`` (N >= 1) or a scheduler address (``tcp://host:port``, ``host:port``); InputError otherwise."""
    text = str(address).strip()
    m = LOCAL_RE.match(text)
    if m and int(m.group(1)) >= 1:
        return text
    if not m and ADDRESS_RE.match(text):
        return text
    raise InputError(f"--dask: expected a scheduler address (tcp://HOST:PORT) or local:N with N >= 1, got {address!r}")


@contextlib.contextmanager
def dask_client(address: str) -> Iterator[object]:
    """A ``distributed.Client`` on ``address`` (see :func:`check_address`); a ``local:N`` cluster is started here
    and closed on exit. InputError when the scheduler cannot be reached or has no workers."""
    address = check_address(address)
    try:
        from distributed import Client, LocalCluster  # lazy: only runs that ask for Dask import it
    except ImportError:
        raise InputError("--dask needs the `distributed` package: pip install distributed") from None
    m = LOCAL_RE.match(address)
    with contextlib.ExitStack() as stack:
        if m:
            cluster = stack.enter_context(LocalCluster(n_workers=int(m.group(1)), threads_per_worker=1,
                                                       processes=True, dashboard_address=None))
            target = cluster
        else:
            target = address if "://" in address else f"tcp://{address}"
        try:
            client = stack.enter_context(Client(target, timeout=f"{CONNECT_TIMEOUT_S}s"))
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--dask: cannot reach the Dask scheduler at {address} ({exc})") from None
        try:
            client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except TimeoutError:
            raise InputError(f"--dask: the scheduler at {address} has no workers") from None
        yield client

"""The Ray backend of ``generate(backend="ray")``: one Ray task per shard (``_run_ray``) on a cluster that is
first awaited for a bounded time (``wait_for_cluster``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

#: how long ``generate(backend="ray", address=...)`` waits for the cluster at ``address`` to accept a connection
#: before it gives up (seconds): a cluster that is still starting gets this long, one that does not exist fails
#: in one line instead of Ray's own minutes of retries
RAY_CONNECT_TIMEOUT_S = 30.0


def ray_endpoint(address: str) -> tuple[str, int] | None:
    """(host, port) that a Ray ``address`` names: "host:port", "ray://host:port" (Ray Client) or "[v6]:port";
    None for "auto" and "local" (Ray finds those itself). Raises ``ValueError`` naming ``--address`` otherwise.

    >>> ray_endpoint("ray://head.example:10001"), ray_endpoint("10.0.0.2:6379"), ray_endpoint("auto")
    (('head.example', 10001), ('10.0.0.2', 6379), None)
    """
    if address in ("auto", "local"):
        return None
    rest = address.split("://", 1)[1] if "://" in address else address
    host, sep, port = rest.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--address must be host:port, ray://host:port or auto, got {address!r}")
    return host, int(port)


def wait_for_cluster(address: str, timeout_s: float | None = None) -> None:
    """Return once the Ray cluster at ``address`` accepts a TCP connection (``ray_endpoint``); raise
    ``ValueError`` (one line naming ``--address``) when none does within ``timeout_s`` seconds (default
    ``RAY_CONNECT_TIMEOUT_S``; retrying every second while the deadline allows)."""
    import socket
    import time

    timeout_s = RAY_CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
    end = ray_endpoint(address)
    if end is None:
        return
    deadline = time.monotonic() + timeout_s
    why = "no answer"
    while True:
        left = deadline - time.monotonic()
        try:
            with socket.create_connection(end, timeout=max(0.1, min(5.0, left))):
                return
        except OSError as e:  # refused, unreachable, unknown host, timed out
            why = e.strerror or type(e).__name__
        if time.monotonic() + 1.0 >= deadline:
            raise ValueError(f"--address: no Ray cluster answered at {address!r} within {timeout_s:g} s ({why})")
        time.sleep(1.0)


def _run_ray(shard_task, cfg, seed, todo, n_groups, out: Path, device, address, workers, images, compile,
             on_done) -> None:
    """Run ``shard_task`` (``generate._ray_shard``: one shard) as one Ray task per shard of ``todo``; ``on_done(k,
    entry)`` as each finishes."""
    import ray  # the ray extra: a ModuleNotFoundError names it (errors.missing_extra)
    started = not ray.is_initialized()
    if started:
        kw = {"address": address} if address else {"num_cpus": workers or os.cpu_count() or 1}
        ray.init(include_dashboard=False, log_to_driver=False, **kw)
    try:
        opts: dict[str, Any] = {"num_cpus": 1, "num_gpus": 1 if str(device).startswith("cuda") else 0, "max_retries": 2}
        task = ray.remote(**opts)(shard_task)
        pending = {task.remote(cfg, seed, k, n_groups, str(out), device, images, compile): k for k in todo}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                k = pending.pop(ref)
                on_done(k, ray.get(ref))
    finally:
        if started:
            ray.shutdown()

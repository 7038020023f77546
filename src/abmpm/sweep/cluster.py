"""Sweeps on Ray: importing it, finding and connecting to a cluster (an address
nobody answers at is refused at once), and the loop that submits each run as a Ray
task and collects the rows as they finish."""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from typing import Any

from abmpm.errors import AbmpmError

RAY_MISSING = "--ray needs ray: pip install 'abmpm[sweep]'"


# --------------------------------------------------------------------------- connecting


def import_ray():
    """The ray module, or AbmpmError telling how to install it."""
    try:
        import ray
    except ImportError:
        raise AbmpmError(RAY_MISSING) from None
    return ray


_NO_CLUSTER = "is a cluster running there? (start one with `ray start --head`)"
_AUTH_HINT = f"{_NO_CLUSTER}; a cluster with token authentication also needs RAY_AUTH_MODE=token here"


def _reachable(address: str, timeout: float = 5.0) -> bool | None:
    """Whether something listens at ``host:port`` (``ray://host:port`` too); None when
    the address is not of that form. Ray itself retries an unreachable address for
    many minutes."""
    text = address.split("://", 1)[-1].rstrip("/")
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return None
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            return True
    except OSError:
        return False


def _latest_local_cluster() -> str | None:
    """The address of the cluster last started with ``ray start`` on this machine
    (Ray's own record, which outlives a cluster that was killed), or None."""
    try:
        from ray._private.utils import read_ray_address

        return read_ray_address() or None
    except Exception:  # a Ray version without it: let ray.init() decide
        return None


def _init_ray(ray, address: str) -> bool:
    """Connect (or start) Ray unless this process already is; True if we did.

    ``auto``: the cluster in $RAY_ADDRESS, else the latest one started on this machine
    with ``ray start`` if it is still running, else a new local instance. (That is
    ``ray.init()``, which, unlike us, waits for minutes on a cluster that was killed;
    ``ray.init(address="auto")`` raises ConnectionError when there is no cluster.)
    ``local``: always a new local instance. Anything else is a cluster address
    (``host:6379``, ``ray://host:10001``).
    """
    if ray.is_initialized():
        return False
    addr: str | None = address
    if address == "auto":
        addr = None
        env = os.environ.get("RAY_ADDRESS")
        if env:
            if _reachable(env) is False:
                raise AbmpmError(f"--ray auto: no Ray cluster answers at $RAY_ADDRESS={env}; {_NO_CLUSTER}")
        else:
            latest = _latest_local_cluster()
            if latest and _reachable(latest) is False:
                addr = "local"  # that cluster is gone: start a local instance
    elif address != "local" and _reachable(address) is False:
        raise AbmpmError(f"--ray {address}: no Ray cluster answers at {address}; {_NO_CLUSTER}")
    try:
        ray.init(address=addr, logging_level=logging.WARNING, log_to_driver=True)
    except (ConnectionError, ValueError, RuntimeError) as exc:
        msg = " ".join(str(exc).split())
        raise AbmpmError(f"--ray {address}: cannot connect to Ray: {msg}; {_AUTH_HINT}") from None
    return True


# --------------------------------------------------------------------------- tasks


def _ray_device(ray, device: str | None, scene) -> tuple[str, int]:
    """(device for the task, GPUs it asks for). Ray hands a task its GPU as cuda:0
    (CUDA_VISIBLE_DEVICES); no device: cuda when the cluster has a GPU."""
    want = device if device is not None else scene.simulation.device
    if want in (None, "", "auto"):
        want = "cuda" if ray.cluster_resources().get("GPU", 0) >= 1 else "cpu"
    return ("cuda", 1) if str(want).startswith("cuda") else (str(want), 0)


def _sweep_on_ray(ray, task, plan, out, frames, device, threads, preview, on_start, done) -> None:
    """Submit every combination as a Ray task running ``task`` (``run_one``'s
    arguments); hand each row to ``done`` as it comes."""
    remote = ray.remote(task)
    pending: dict[Any, int] = {}
    n = len(plan.runs)
    for i, (name, combo) in enumerate(plan.runs):
        dev, gpus = _ray_device(ray, device, plan.source.build(combo))
        cpus = 1 if gpus else (threads or 1)
        ref = remote.options(num_cpus=cpus, num_gpus=gpus, name=f"abmpm-sweep:{name}", max_retries=0).remote(
            plan.source, combo, str(out / name), frames=frames, device=dev,
            threads=None if gpus else cpus, preview=preview, name=name,
        )
        pending[ref] = i
        if on_start:
            on_start(i + 1, n, name)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            ref = ready[0]
            i = pending.pop(ref)
            name, combo = plan.runs[i]
            try:
                row = ray.get(ref)
            except Exception as exc:  # the task died (worker crash, lost node, ...)
                msg = " ".join(str(exc).split())
                row = {"run": name, **combo, "status": "error",
                       "message": f"Ray task failed: {type(exc).__name__}: {msg[:500]}"}
            done(i, row)
    except BaseException:  # Ctrl-C: do not leave the other runs going
        for ref in pending:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        raise

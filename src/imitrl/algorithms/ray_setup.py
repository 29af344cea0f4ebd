"""Starting Ray for DAgger's workers: a local instance or a cluster (:func:`init_ray`),
the workers' share of the machine (:data:`WORKER_THREADS`), and TorchRL's weight-sync
wait raised for slow-starting workers (:func:`patient_weight_sync`).
"""

from __future__ import annotations

import os
import socket
import sys
import tempfile

__all__ = ["RAY_INSTALL_HINT", "WEIGHT_SYNC_TIMEOUT_S", "WORKER_THREADS", "check_address",
           "import_ray", "init_ray",
           "patient_weight_sync"]  # fmt: skip

WORKER_THREADS = 1
"""torch threads (and Ray CPUs, ``num_cpus``) of each worker: workers run side by side,
so more than one each would oversubscribe the cores (``benchmarks/threads.py``)"""

WEIGHT_SYNC_TIMEOUT_S = 600
"""how long the driver waits for the workers to join the weight-sync process group"""


def patient_weight_sync() -> None:
    """Raise TorchRL's fixed 60 s wait for Ray workers to join the weight sync to
    :data:`WEIGHT_SYNC_TIMEOUT_S` (a worker on a loaded machine starts slowly), once, in
    the one place imitrl builds Ray collectors (the private constant is set in
    :func:`imitrl.compat.raise_ray_weight_sync_wait`)."""
    from imitrl.compat import raise_ray_weight_sync_wait

    raise_ray_weight_sync_wait(WEIGHT_SYNC_TIMEOUT_S)


RAY_INSTALL_HINT = "pip install 'imitrl[distributed]'"


def import_ray():
    try:
        import ray
    except ImportError as err:
        raise ImportError(f"running DAgger on Ray workers needs ray: {RAY_INSTALL_HINT}") from err
    return ray


_RAY_TEMP_MAX = 24  # longest <tempdir>/ray that leaves room for Ray's session socket paths


def init_ray(
    num_cpus: int | None, *, address: str | None = None, runtime_env: dict | None = None
) -> bool:
    """Start a local Ray instance (``address`` None) or connect to a cluster, unless Ray runs.

    Local: ``num_cpus`` logical CPUs, no dashboard. ``runtime_env`` None: workers get
    ``PYTHONPATH`` = this process's ``sys.path``, so they import imitrl and the user's
    modules (on a cluster, give a ``runtime_env`` with a ``working_dir`` instead, or
    install them on the nodes). Returns True when this call started or connected Ray
    (the caller then shuts it down), False when Ray was already initialised.
    """
    ray = import_ray()
    if ray.is_initialized():
        return False
    if runtime_env is None:
        paths = [os.path.abspath(p or os.curdir) for p in sys.path]
        runtime_env = {"env_vars": {"PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}}
    options: dict[str, object] = {"runtime_env": runtime_env, "logging_level": "warning"}
    if address is None:
        options.update(num_cpus=num_cpus, include_dashboard=False)
        # Ray puts its AF_UNIX sockets under <tempdir>/ray/session_<time>_<pid>/sockets/,
        # and a socket path may not exceed 107 bytes: under a long TMPDIR (a test's
        # tmp_path, say) a local start fails, so Ray's own files go to a short dir then
        if len(os.path.join(tempfile.gettempdir(), "ray")) > _RAY_TEMP_MAX and os.path.isdir(
            "/tmp"
        ):
            options["_temp_dir"] = "/tmp/ray"
    else:
        check_address(address)
    try:
        ray.init(address=address, **options)
    except (ConnectionError, TimeoutError) as err:  # one line, not Ray's traceback
        raise ValueError(f"--address {address}: Ray could not connect ({err})") from err
    return True


_CONNECT_S = 5.0
"""seconds a cluster's address has to accept a connection before Ray is asked to join"""


def check_address(address: str) -> None:
    """ValueError unless something accepts a TCP connection at ``address`` (``host:port``
    or ``ray://host:port``; ``auto`` and other forms are Ray's to resolve): Ray itself
    retries an address nobody listens at for minutes."""
    plain = address.removeprefix("ray://")
    host, sep, port = plain.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return
    try:
        socket.create_connection((host, int(port)), timeout=_CONNECT_S).close()
    except OSError as err:
        raise ValueError(
            f"--address {address}: nothing accepts a connection at {host}:{port} "
            f"({err.strerror or err}); start the cluster first (ray start --head) or "
            "leave --address out for a local Ray"
        ) from None

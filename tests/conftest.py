"""Shared fixtures: devices to parametrize over and the (slow to build) default body."""
from __future__ import annotations

import os

import pytest

os.environ.setdefault("TQDM_DISABLE", "1")


def available_devices() -> list[str]:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    return ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


@pytest.fixture(scope="session")
def anny_body():
    from simulate.body import load_body_model

    return load_body_model("anny")


@pytest.fixture
def load_bench():
    """Imports ``bench/<name>.py`` (a script, not a package module) under a test-only name."""
    import importlib.util
    from pathlib import Path

    def load(name: str):
        path = Path(__file__).parents[1] / "bench" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(f"{name}_under_test", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture
def unwritable_dir(tmp_path):
    """A directory this process cannot create files in: a mode 0555 directory, or for root (whom
    permission bits do not stop) a sysfs directory; skips where neither refuses a write."""
    from pathlib import Path

    candidates = []
    if os.geteuid() != 0:
        locked = tmp_path / "read-only"
        locked.mkdir()
        locked.chmod(0o555)
        candidates.append(locked)
    candidates.append(Path("/sys/kernel"))
    for directory in candidates:
        probe = directory / f".probe-{os.getpid()}"
        try:
            probe.write_bytes(b"")
            probe.unlink()
        except OSError:
            yield directory
            break
    else:
        pytest.skip("no directory refuses writes here")
    if os.geteuid() != 0:
        (tmp_path / "read-only").chmod(0o755)


@pytest.fixture
def spawn_ranks():
    """``spawn_ranks(fn, *args, ranks=2, timeout_s=120.0, what="...")`` runs ``fn(rank, ranks, port,
    *args)`` in ``ranks`` spawned processes (``port``: a free local port for their process group)
    and fails the test when they do not finish within ``timeout_s``; skips without gloo."""
    import socket
    import time

    import torch

    if not torch.distributed.is_available() or not torch.distributed.is_gloo_available():
        pytest.skip("torch.distributed with gloo is not available")

    def spawn(fn, *args, ranks: int = 2, timeout_s: float = 120.0, what: str = "the ranks") -> None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        context = torch.multiprocessing.start_processes(fn, args=(ranks, port, *args), nprocs=ranks, join=False,
                                                        start_method="spawn")
        deadline = time.monotonic() + timeout_s
        while not context.join(timeout=1.0):
            if time.monotonic() > deadline:
                for process in context.processes:
                    process.kill()
                pytest.fail(f"{what} did not finish within {timeout_s:.0f} s")

    return spawn

"""An `mlflow server` on loopback, started as `make mlflow-server` starts one, and ended by its
process group: for checks that need a real tracking server (`make bench-tracking`, tests).

Why a process group: `mlflow server` runs its web workers as child processes; ending only the
command's own pid would leave them serving the port.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from harness.common.errors import RetainError


def free_port() -> int:
    """A port on 127.0.0.1 nobody listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _mlflow_command() -> list[str]:
    script = Path(sys.executable).with_name("mlflow")  # the venv's, as the Makefile runs it
    return [str(script)] if script.exists() else [sys.executable, "-m", "mlflow"]


@dataclass
class TrackingServer:
    """`mlflow server` with its runs in `<root>/mlflow.db` and artifacts in `<root>/artifacts`
    (served through the server), the Makefile's mlflow-server layout."""

    root: Path
    port: int = field(default_factory=free_port)
    workers: int | None = None  # None: mlflow's default, as `make mlflow-server` runs it
    process: subprocess.Popen | None = None
    starts: int = 0

    @property
    def uri(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def backend(self) -> str:
        return f"sqlite:///{self.root.resolve() / 'mlflow.db'}"

    def start(self, timeout: float = 300.0) -> TrackingServer:
        """Start it (again, on the same port and store) and wait until it answers."""
        self.root.mkdir(parents=True, exist_ok=True)
        cmd = [*_mlflow_command(), "server", "--backend-store-uri", self.backend,
               "--artifacts-destination", str(self.root.resolve() / "artifacts"),
               "--serve-artifacts", "--host", "127.0.0.1", "--port", str(self.port)]
        if self.workers:
            cmd += ["--workers", str(self.workers)]
        self.starts += 1
        log = open(self.root / f"server-{self.starts}.log", "w")
        self.process = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                        start_new_session=True)
        log.close()
        self._wait_healthy(timeout)
        return self

    def _wait_healthy(self, timeout: float) -> None:
        import requests

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RetainError(f"mlflow server on port {self.port} exited with status "
                                  f"{self.process.returncode}: {self._last_log_line()}")
            try:
                if requests.get(f"{self.uri}/health", timeout=2).ok:
                    return
            except requests.RequestException:
                pass
            time.sleep(0.2)
        self.stop()
        raise RetainError(f"mlflow server on port {self.port} did not answer within "
                          f"{timeout:.0f}s: {self._last_log_line()}")

    def _last_log_line(self) -> str:
        lines = (self.root / f"server-{self.starts}.log").read_text().strip().splitlines()
        return lines[-1][:200] if lines else "no output"

    def stop(self, kill: bool = False) -> None:
        """End its process group: SIGTERM (or SIGKILL, a crash), SIGKILL if still there."""
        if self.process is None or self.process.poll() is not None:
            return
        pgid = self.process.pid  # start_new_session: the group's id is the command's pid
        try:
            os.killpg(pgid, signal.SIGKILL if kill else signal.SIGTERM)
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(pgid, signal.SIGKILL)
                self.process.wait()
            os.killpg(pgid, signal.SIGKILL)  # workers that outlived the command
        except ProcessLookupError:
            pass

    def __enter__(self) -> TrackingServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

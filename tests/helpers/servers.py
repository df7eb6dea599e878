"""Real server processes for tests: started on a free loopback port, waited for, stopped with
their whole process group, bounded in time."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import pytest


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mlflow_command() -> list[str]:
    cli = Path(sys.executable).with_name("mlflow")
    return [str(cli)] if cli.exists() else [sys.executable, "-m", "mlflow"]


def server_env(**extra) -> dict:
    # MLflow starts its servers as `bash -c "exec uvicorn ..."`: uvicorn must be on PATH, which a
    # venv's python run without activating the venv does not arrange.
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    return {**os.environ, "PATH": path, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", **extra}


def get(url: str, timeout: float = 30.0, **params):
    """(status, decoded JSON) of a GET with query parameters."""
    query = f"?{urllib.parse.urlencode(params)}" if params else ""
    try:
        with urllib.request.urlopen(url + query, timeout=timeout) as response:
            return response.status, json.loads(response.read() or b"{}")
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"{}")


def post(url: str, body: dict, timeout: float = 60.0):
    """(status, decoded JSON) of a JSON POST."""
    request = urllib.request.Request(
        url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"}, method="POST"
    )
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"{}")


def group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM to the server's process group, SIGKILL after 10 s if anything is left."""
    for sig, grace in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        if not group_alive(proc.pid):
            break
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline and group_alive(proc.pid):
            try:
                proc.wait(timeout=0.2)  # reap the leader so the group can empty
            except subprocess.TimeoutExpired:
                pass
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        pass


@contextmanager
def running(command: list[str], base_url: str, log_path: Path, cwd: Path, env: dict, startup_s: float = 90.0):
    """Start `command` in its own process group, wait until GET base_url/health answers 200,
    yield the seconds start-up took, and stop the whole group afterwards (asserting it is gone)."""
    with open(log_path, "wb") as log:
        started = time.perf_counter()
        proc = subprocess.Popen(
            command,
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            cwd=cwd,
            start_new_session=True,
        )
    try:
        deadline = time.monotonic() + startup_s
        while True:
            if proc.poll() is not None:
                pytest.fail(
                    f"the server exited with {proc.returncode} before answering "
                    f"/health:\n{log_path.read_text()[-4000:]}"
                )
            try:
                with urllib.request.urlopen(f"{base_url}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                pass
            if time.monotonic() > deadline:
                pytest.fail(
                    f"the server did not answer /health within {startup_s:.0f} "
                    f"s:\n{log_path.read_text()[-4000:]}"
                )
            time.sleep(0.5)
        yield time.perf_counter() - started
    finally:
        stop(proc)
    assert not group_alive(proc.pid), "a server process survived SIGKILL"

"""Separate processes without paying for Python, torch, MLflow and Lightning on each one.

A table of 88 bad inputs spent 90 s of the suite mostly importing those libraries 88 times over, and
every two-process DDP test about 8 s importing Lightning in both ranks. Here each command or rank
still runs in a process of its own, with its own working directory, environment, exit status and
captured output. But that process is forked from a multiprocessing fork server that has imported the
libraries once and run nothing. Because nothing has run, no lock or thread pool is left half-used when
it forks.

The real start-up paths are still checked elsewhere:
- the console script: `test_console_script_refuses_like_the_module`;
- what a refusal imports: `test_architecture`;
- Lightning's own DDP launcher: `run_ddp_worker(..., launch="subprocess")`;
- torchrun: `test_multinode`.
"""

from __future__ import annotations

import multiprocessing
import os
import runpy
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from tests.helpers.servers import free_port

PRELOAD = ["torch", "numpy", "omegaconf", "mmm.cli.app", "mmm.training.configs", "mlflow", "lightning"]


def _fork_context():
    # One fork server per test session: the first start fixes what it preloads.
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)
    return context


def _enter(cwd: str | None, env: dict[str, str], argv: list[str]) -> None:
    """Become the process a command line would have started: its folder, environment and argv."""
    if cwd is not None:
        os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    if env.get("PYTHONWARNINGS") == "ignore":  # read at interpreter start-up, which a fork skips
        warnings.simplefilter("ignore")
    sys.argv = argv


def _exit_status(e: SystemExit) -> int:
    """What the interpreter exits with for `e`; a message is printed as it would print it."""
    if isinstance(e.code, int) or e.code is None:
        return e.code or 0
    print(e.code, file=sys.stderr)
    return 1


def _main_in_this_process(argv: list[str], cwd: str, env: dict[str, str]) -> tuple[int, str, str]:
    """What `python -m mmm.cli ARGV` does, in this (fresh, forked) process: (exit status, stdout, stderr)."""
    _enter(cwd, env, ["mmm", *argv])
    # The descriptors themselves, not only sys.stdout/sys.stderr: so that anything written
    # to them is captured too (C extensions, handlers holding the old stream objects).
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        os.dup2(out.fileno(), 1)
        os.dup2(err.fileno(), 2)
        try:
            from mmm.cli.app import main

            status = main(argv)
        except SystemExit as e:  # argparse exits 2 itself
            status = _exit_status(e)
        except BaseException:  # as the interpreter ends on an uncaught exception
            traceback.print_exc()
            status = 1
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
        texts = []
        for f in (out, err):
            f.seek(0)
            texts.append(f.read().decode("utf-8", "replace"))
    return status, texts[0], texts[1]


class ForkedCLI:
    """`with ForkedCLI(workers) as cli: cli.run(argv, cwd, env)`; one fresh process per command."""

    def __init__(self, workers: int):
        self._pool = ProcessPoolExecutor(workers, mp_context=_fork_context(), max_tasks_per_child=1)

    def __enter__(self) -> ForkedCLI:
        return self

    def __exit__(self, *exc) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def run(self, argv: list[str], cwd: Path, env: dict[str, str], timeout: float = 300):
        status, stdout, stderr = self._pool.submit(
            _main_in_this_process, list(argv), str(cwd), dict(env)
        ).result(timeout=timeout)
        return subprocess.CompletedProcess(["mmm", *argv], status, stdout, stderr)


def _script_as_rank(script: str, args: list[str], env: dict[str, str], stderr_path: str) -> None:
    """`python SCRIPT ARGS` in this process, its stderr into `stderr_path`; the process's exit code is
    the script's (multiprocessing reports SystemExit and prints an uncaught exception's traceback)."""
    _enter(None, env, [script, *args])
    sys.path.insert(0, str(Path(script).parent))  # as `python script` puts the script's folder first
    with open(stderr_path, "wb") as err:
        os.dup2(err.fileno(), 2)
    runpy.run_path(script, run_name="__main__")


def run_script_as_ranks(
    script: Path, args: list[str], env: dict[str, str], ranks: int, timeout: float
) -> list[tuple[int | None, str]]:
    """Start `python SCRIPT ARGS` once per rank of a one-node, `ranks`-process DDP run, with the
    environment Lightning's launcher gives each process it starts (MASTER_ADDR, MASTER_PORT, NODE_RANK,
    LOCAL_RANK), so that a Trainer in the script joins them instead of launching its own.

    Returns [(exit code, or None when it was killed at the timeout, stderr)] per rank. One rank
    failing leaves the others waiting in a collective: all are killed at the timeout."""
    context = _fork_context()
    port = free_port()
    processes, errors = [], []
    with tempfile.TemporaryDirectory() as folder:
        for rank in range(ranks):
            errors.append(os.path.join(folder, f"rank{rank}.stderr"))
            rank_env = {
                **env,
                "MASTER_ADDR": "127.0.0.1",
                "MASTER_PORT": str(port),
                "NODE_RANK": "0",
                "LOCAL_RANK": str(rank),
            }
            process = context.Process(target=_script_as_rank, args=(str(script), args, rank_env, errors[-1]))
            process.start()
            processes.append(process)
        deadline = time.monotonic() + timeout
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                for p in processes:
                    p.kill()
                    p.join()
                break
        results = []
        for process, path in zip(processes, errors):
            code = None if process.exitcode in (None, -9) else process.exitcode
            results.append((code, Path(path).read_text(errors="replace") if os.path.exists(path) else ""))
    return results

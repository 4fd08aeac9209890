"""Many independent items — materials, benchmarks, scenes, frames, sweep points — on a local process pool or a Ray
cluster, with results identical to a serial run.

A feature only describes its items (:class:`Item`: a key, an importable ``module:function``, plain arguments, and
the file whose existence means the item is done); :func:`run_items` owns the rest:

* **where** — ``workers = 0``: in this process, one after another; ``workers ≥ 1``: a local process pool started
  with ``spawn`` (Dr.Jit/LLVM state is not fork-safe); ``ray`` set: the same items as Ray tasks (``"local"`` starts a
  Ray instance on this machine, ``"auto"`` or an address joins a running cluster);
* **the same result anywhere** — every worker imports :mod:`mi_plugins` (Mitsuba's plugin registry is per process
  and per variant; Ray reuses worker processes, so it is done once per process) and sets its own Dr.Jit and torch
  thread counts (Dr.Jit reads no environment variable for it; Ray's ``OMP_NUM_THREADS`` does not reach it). With one
  Dr.Jit thread per item, renders and fits are bit-identical wherever they ran;
* **failures** — an item that raises (or whose worker dies) is retried ``retries`` times, then reported with its
  key and a one-line error; the other items finish; :class:`BatchReport` summarises;
* **resume** — an item whose ``output`` file exists, stamped by a finished run of the very same item (function and
  arguments, settings included), is skipped: a killed batch continues where it stopped, and a batch run again with
  other settings runs again (the item's own checkpoint then decides whether it can continue);
* **one progress bar** over all items.

Items run in any order on a pool; results come back in the items' order.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import importlib
import multiprocessing as mp
import os
import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from . import validate
from .errors import FailureError, UsageError
from .progress import progress_bar


@dataclass(frozen=True)
class Item:
    """One independent unit of work. ``fn`` is ``"module:function"``, called as ``fn(*args, **kwargs)``.

    Arguments must be picklable and mean the same on every machine (paths on storage the workers share).
    The function returns something JSON-able (a summary); its real output goes to files.
    """

    key: str  #: names the item in progress, errors and the summary
    fn: str
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    output: str | None = None  #: a file that exists once the item is done (resume skips the item then)
    loader: str | None = None  #: "module:function" that reads ``output`` back as the value of a skipped item


@dataclass
class PoolSettings:
    workers: int = 0  #: 0: this process, serially; n ≥ 1: n worker processes (or n Ray tasks at a time)
    ray: str | None = None  #: None: local processes; "local": start Ray here; "auto" or an address: join a cluster
    threads: int = 1  #: Dr.Jit and torch threads per item (1: bit-reproducible wherever the item runs)
    retries: int = 1  #: extra attempts for a failing item

    def __post_init__(self):
        validate.integer("workers", self.workers, 0, 4096)
        validate.integer("threads", self.threads, 0, 4096)
        validate.integer("retries", self.retries, 0, 100)
        if self.ray is not None and self.workers < 1:
            raise UsageError("workers must be ≥ 1 with ray (how many tasks run at a time)")
        if self.ray is not None:
            check_ray_address(self.ray)  # before any work: an unreachable cluster fails in seconds, in one line


RAY_CONNECT_S = 3.0  #: how long reaching a cluster's address may take before it is refused


def _ray_host_port(address: str) -> tuple[str, int]:
    """(host, port) of a Ray address ``HOST:PORT`` or ``ray://HOST:PORT``; a malformed one is refused by name."""
    rest = address.split("://", 1)[1] if "://" in address else address
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UsageError(f"--ray {address}: not 'local', 'auto' or HOST:PORT")
    return host.strip("[]"), int(port)


def check_ray_address(address: str, timeout: float = RAY_CONNECT_S) -> None:
    """Refuse, naming ``--ray``, a cluster address that nothing answers at within ``timeout`` seconds ("local"
    starts Ray here; "auto" must find a cluster this machine started, as Ray's own lookup does)."""
    import socket

    if address == "local":
        return
    if address == "auto":
        found = os.environ.get("RAY_ADDRESS") or _current_cluster()
        if not found:
            raise UsageError("--ray auto: no Ray cluster runs on this machine (start one with `ray start --head`, or "
                             "give HOST:PORT)")
        address = found
    host, port = _ray_host_port(address)
    t0 = time.monotonic()
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except OSError as exc:
        why = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or type(exc).__name__)
        raise UsageError(f"--ray {address}: cannot reach {host}:{port} ({why}; waited at most {timeout:g} s)") from None
    if "://" not in address:  # a GCS address (ray:// is Ray Client's own protocol): ask it what Ray asks first
        _probe_gcs(address, host, port, max(0.5, timeout - (time.monotonic() - t0)))


def _probe_gcs(address: str, host: str, port: int, timeout: float) -> None:
    """Refuse a port that answers but is no Ray cluster this client may join (another service, a proxy, a cluster
    wanting another auth token), which ``ray.init`` would retry for 20–40 s with a warning a second: the cluster id
    Ray's client asks for first, within ``timeout``."""
    try:
        from ray._raylet import GcsClient
    except ImportError:
        return  # without Ray, the connection names the missing package
    box: dict = {}

    def probe():
        try:
            GcsClient(address=f"{host}:{port}")
            box["ok"] = True
        except Exception as exc:  # Ray's RpcError and its kin
            box["error"] = " ".join(str(exc).split())[:200]

    with _quiet_stderr():  # Ray's C++ client logs each retry to the terminal
        t = threading.Thread(target=probe, name="photoreal-ray-probe", daemon=True)
        t.start()
        t.join(timeout)
    if "ok" in box:
        return
    # ray.init begins with this very request and would retry it for 20–40 s: its answer is the connection's
    why = box.get("error") or f"no answer within {timeout:.1f} s"
    if "Unauthenticated" in why or "AuthToken" in why:
        raise UsageError(f"--ray {address}: the Ray cluster there wants its authentication token: set "
                         "RAY_AUTH_MODE=token here, with the cluster's token in ~/.ray/auth_token or RAY_AUTH_TOKEN "
                         f"({why})")
    raise UsageError(f"--ray {address}: {host}:{port} answers, but not as a Ray cluster ({why})")


@contextlib.contextmanager
def _quiet_stderr():
    """File descriptor 2 to /dev/null (C++ libraries write there directly), unless the user asked for Ray's logs
    (PHOTOREAL_DEBUG or RAY_BACKEND_LOG_LEVEL set)."""
    if os.environ.get("PHOTOREAL_DEBUG", "") not in ("", "0") or "RAY_BACKEND_LOG_LEVEL" in os.environ:
        yield
        return
    sys.stderr.flush()
    saved = os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


def _current_cluster() -> str | None:
    """The address Ray's ``ray start`` on this machine recorded, if any."""
    import tempfile

    for folder in {Path(tempfile.gettempdir()) / "ray", Path("/tmp/ray")}:
        try:
            text = (folder / "ray_current_cluster").read_text().strip()
        except OSError:
            continue
        if text:
            return text
    return None


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


@dataclass
class ItemResult:
    key: str
    ok: bool
    value: Any = None
    error: str | None = None  #: one line: the exception's type and message
    seconds: float = 0.0  #: of the last attempt, in the worker
    attempts: int = 0
    skipped: bool = False  #: done before (its output existed)
    where: str = ""  #: "serial", "pool pid N" or "ray node …"


@dataclass
class BatchReport:
    results: list[ItemResult]
    seconds: float  #: wall time of the batch

    @property
    def failed(self) -> list[ItemResult]:
        return [r for r in self.results if not r.ok]

    @property
    def ran(self) -> list[ItemResult]:
        return [r for r in self.results if r.ok and not r.skipped]

    @property
    def skipped(self) -> list[ItemResult]:
        return [r for r in self.results if r.skipped]

    def summary(self) -> str:
        s = (f"{len(self.results)} items: {len(self.ran)} done, {len(self.skipped)} skipped (done before), "
             f"{len(self.failed)} failed in {self.seconds:.1f} s")
        return s + "".join(f"\n  failed: {r.key}: {r.error}" for r in self.failed)

    def raise_if_failed(self) -> None:
        """A batch with a failed item is a failure (exit code 1), after every other item finished."""
        if self.failed:
            raise FailureError(self.summary().replace("\n", "; "))


# -- the worker side ---------------------------------------------------------------------------------------------

_WORKER_THREADS: int | None = None


def _prepare(threads: int) -> None:
    """Once per worker process (and again when the thread count changes)."""
    global _WORKER_THREADS
    if _WORKER_THREADS == threads:
        return
    import mi_plugins  # noqa: F401  (libLLVM, variant, plugin registry of this process)
    import drjit as dr

    if threads:
        dr.set_thread_count(threads)
        try:
            import torch

            torch.set_num_threads(threads)
        except ImportError:
            pass
    _WORKER_THREADS = threads


def _resolve(fn: str):
    module, _, name = fn.partition(":")
    if not module or not name:
        raise UsageError(f"item function {fn!r} must be 'module:function'")
    return getattr(importlib.import_module(module), name)


def execute(item: Item, threads: int, where: str = "", started: str | None = None) -> ItemResult:
    """Run one item in this process (the pool's and Ray's worker body); exceptions become the result's error.

    ``started``: a file to create first, so that the driver knows which items a dying worker had begun.
    """
    if started:
        Path(started).touch()
    t0 = time.perf_counter()
    try:
        _prepare(threads)
        value = _resolve(item.fn)(*item.args, **item.kwargs)
        return ItemResult(item.key, True, value, seconds=time.perf_counter() - t0, where=where or f"pid {os.getpid()}")
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # an item's failure is data, not the batch's end
        msg = " ".join(str(exc).split()) or type(exc).__name__
        if os.environ.get("PHOTOREAL_DEBUG", "") not in ("", "0"):
            msg += "\n" + traceback.format_exc()
        return ItemResult(item.key, False, error=f"{type(exc).__name__}: {msg}",
                          seconds=time.perf_counter() - t0, where=where or f"pid {os.getpid()}")


def _exit_with_parent(parent: int, period: float = 0.5) -> None:
    """End this worker once its driver process is gone (killed, crashed): the pool's workers are not its
    children's children, so nothing else stops them, and an orphan would finish its item and write into folders a
    rerun may already own (seen 2026-11-27: a killed ``photoreal bench morph`` left its two workers writing a suite's
    trial folders and ``metrics.json`` into the work folder of the next run for half an hour)."""

    def watch():
        while os.getppid() == parent:
            time.sleep(period)
        os._exit(1)  # no cleanup: the item's outputs are written atomically, a half-done one is simply absent

    threading.Thread(target=watch, name="photoreal-parent-watch", daemon=True).start()


def _pool_init(threads: int, parent: int | None = None) -> None:
    if parent is not None:
        _exit_with_parent(parent)
    # tqdm's default lock is a multiprocessing semaphore; a worker terminated on Ctrl-C could not release it, and
    # the driver's resource tracker would warn of it at exit. A worker's bars (disabled) need only a thread lock.
    import tqdm

    tqdm.tqdm.set_lock(threading.RLock())
    _prepare(threads)


# -- the driver side ---------------------------------------------------------------------------------------------


def _digest(item: Item) -> str:
    from .records import json_digest

    return json_digest([item.fn, list(item.args), item.kwargs])


def _stamp(item: Item) -> Path:
    out = Path(item.output)
    return out.with_name(f".{out.name}.item")


def _done(item: Item) -> bool:
    """Its output exists and was made by this very item (same function, arguments and settings)."""
    if item.output is None or not Path(item.output).is_file():
        return False
    try:
        return _stamp(item).read_text() == _digest(item)
    except OSError:
        return False


def _mark_done(item: Item) -> None:
    if item.output is not None and Path(item.output).is_file():
        from .files import write_text

        write_text(_stamp(item), _digest(item))


def _load(item: Item):
    return _resolve(item.loader)(item.output) if item.loader else None


def run_items(items: Sequence[Item], s: PoolSettings | None = None, desc: str = "items",
              show_progress: bool = True) -> BatchReport:
    """Run every item not done yet (see the module docstring); never raises for an item's failure."""
    s = s or PoolSettings()
    keys = [it.key for it in items]
    if len(set(keys)) != len(keys):
        raise UsageError(f"{desc}: item keys must be unique")
    t0 = time.perf_counter()
    results: dict[str, ItemResult] = {}
    todo = []
    for it in items:
        if _done(it):
            results[it.key] = ItemResult(it.key, True, _load(it), skipped=True, where="done before")
        else:
            todo.append(it)
    with progress_bar(total=len(items), desc=desc, unit="item", disable=not show_progress) as bar:
        bar.update(len(items) - len(todo))
        if todo:
            if s.ray is not None:
                runner = _run_ray
            elif s.workers >= 1:
                runner = _run_pool
            else:
                runner = _run_serial
            by_key = {it.key: it for it in todo}
            for r in runner(todo, s):
                results[r.key] = r
                if r.ok:
                    _mark_done(by_key[r.key])
                bar.update(1)
                bar.set_postfix(failed=sum(not x.ok for x in results.values()), refresh=False)
    return BatchReport([results[k] for k in keys], time.perf_counter() - t0)


def _run_serial(items: list[Item], s: PoolSettings):
    from .threads import drjit_threads, torch_threads

    with drjit_threads(s.threads or None), torch_threads(s.threads or None):
        import mi_plugins  # noqa: F401

        for it in items:
            for attempt in range(1, s.retries + 2):
                r = _serial_one(it)
                r.attempts = attempt
                if r.ok:
                    break
            yield r


def _serial_one(item: Item) -> ItemResult:
    t0 = time.perf_counter()
    try:
        value = _resolve(item.fn)(*item.args, **item.kwargs)
        return ItemResult(item.key, True, value, seconds=time.perf_counter() - t0, where="serial")
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # as in a worker: SystemExit from an item fails that item, not the batch
        msg = " ".join(str(exc).split()) or type(exc).__name__
        return ItemResult(item.key, False, error=f"{type(exc).__name__}: {msg}", seconds=time.perf_counter() - t0,
                          where="serial")


def _run_pool(items: list[Item], s: PoolSettings):
    """A spawn pool. A worker that dies (crash, out of memory) takes the whole pool down, failing every pending
    item with it. Items that had not begun go to a fresh pool; those that had (each marks its start in a file)
    run again one at a time, each in a process of its own, so that a crash is charged to its own item."""
    import tempfile

    ctx = mp.get_context("spawn")
    attempts = {it.key: 0 for it in items}
    queue, suspects = list(items), []
    with tempfile.TemporaryDirectory(prefix="photoreal-pool-") as marks:
        round_no = 0
        while queue:
            round_no += 1
            ex = cf.ProcessPoolExecutor(max_workers=min(s.workers, len(queue)), mp_context=ctx,
                                        initializer=_pool_init, initargs=(s.threads, os.getpid()))
            try:
                started = {it.key: str(Path(marks) / f"{round_no}-{k}") for k, it in enumerate(queue)}
                futures = {ex.submit(execute, it, s.threads, "", started[it.key]): it for it in queue}
                queue, before = [], len(futures)
                for fut in cf.as_completed(futures):
                    it = futures[fut]
                    try:
                        r = fut.result()
                    except cf.process.BrokenProcessPool:
                        (suspects if Path(started[it.key]).exists() else queue).append(it)
                        continue
                    attempts[it.key] += 1
                    r.attempts = attempts[it.key]
                    if not r.ok and attempts[it.key] <= s.retries:
                        queue.append(it)
                        continue
                    yield r
            except BaseException:  # Ctrl-C, or the caller stopped reading: the workers stop now, not after
                _stop_workers(ex)  # their items (each item's output is written atomically: a cut one is absent)
                raise
            ex.shutdown(wait=True)
            if len(queue) == before and not any(Path(p).exists() for p in started.values()):
                # No item even began: the workers die while starting (e.g. a script that starts a pool at import
                # time without ``if __name__ == "__main__":``, which spawn re-runs in every worker).
                raise FailureError(f"every worker process died before starting an item ({before} items pending); "
                                   "a script that uses the pool must guard its work with if __name__ == '__main__'")
    for it in suspects:
        while True:
            attempts[it.key] += 1
            with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_pool_init,
                                        initargs=(s.threads, os.getpid())) as ex:
                try:
                    r = ex.submit(execute, it, s.threads).result()
                except cf.process.BrokenProcessPool:
                    r = ItemResult(it.key, False, error="its worker process died (a crash or out of memory)")
            r.attempts = attempts[it.key]
            if r.ok or attempts[it.key] > s.retries:
                yield r
                break


def _stop_workers(ex: cf.ProcessPoolExecutor) -> None:
    """Terminate a pool's worker processes and drop its pending items."""
    procs = list((getattr(ex, "_processes", None) or {}).values())
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=3)
        if p.is_alive():  # SIGTERM not acted on in time (e.g. inside a long native call): SIGKILL
            p.kill()
            p.join(timeout=3)
    # no waiting on the pool's own threads: the workers are gone, and a join there is the one wait without a bound
    ex.shutdown(wait=False, cancel_futures=True)


_RAY_STARTED = False


def _ray_connect(address: str, workers: int):
    import ray

    global _RAY_STARTED
    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
            _RAY_STARTED = True
        else:
            ray.init(address=address, include_dashboard=False, log_to_driver=False)
    return ray


def ray_shutdown() -> None:
    """Stop the Ray instance this process started with ``ray="local"`` (a joined cluster keeps running)."""
    global _RAY_STARTED
    if _RAY_STARTED:
        import ray

        ray.shutdown()
        _RAY_STARTED = False


def _ray_task(item: Item, threads: int) -> ItemResult:
    import socket

    return execute(item, threads, where=f"ray {socket.gethostname()} pid {os.getpid()}")


def _run_ray(items: list[Item], s: PoolSettings):
    try:
        ray = _ray_connect(s.ray, s.workers)
    except ImportError:
        raise UsageError("--ray needs Ray: pip install 'ray==2.60.0'") from None
    except Exception as exc:  # ConnectionError and friends: name the address
        raise UsageError(f"--ray {s.ray}: cannot connect ({' '.join(str(exc).split())[:200]})") from None
    # One CPU per task and at most `workers` tasks in flight; retries are ours (max_retries=0), the same for an
    # item that raised and for one whose worker died.
    task = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
    attempts = {it.key: 0 for it in items}
    waiting, refs = list(items), {}
    while waiting or refs:
        while waiting and len(refs) < s.workers:
            it = waiting.pop(0)
            attempts[it.key] += 1
            refs[task.remote(it, s.threads)] = it
        done, _ = ray.wait(list(refs), num_returns=1)
        it = refs.pop(done[0])
        try:
            r = ray.get(done[0])
        except Exception as exc:  # the task's worker died
            r = ItemResult(it.key, False, error=f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}")
        r.attempts = attempts[it.key]
        if not r.ok and attempts[it.key] <= s.retries:
            waiting.append(it)
            continue
        yield r

"""Scale-out: the same items serially, on a spawn process pool and on a local Ray instance give the same bits;
a failing item or a dying worker is reported while the rest finish; a rerun skips what is done."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from foundation import imageio
from foundation.errors import UsageError
from foundation.pool import Item, PoolSettings, ray_shutdown, run_items
from foundation.scene import RenderSettings
from photoreal.cli import main

SCENES = Path(__file__).resolve().parents[2] / "scenes"


def _renders(out: Path, names=("material_test", "josie", "armadillo", "neural_materials")) -> list[Item]:
    items = []
    for k, name in enumerate(names):
        exr = out / f"{k}_{name}.exr"
        items.append(Item(f"{k}_{name}", "foundation.scene:render_item",
                          (str(SCENES / f"{name}.xml"), str(exr), RenderSettings(spp=4, resolution=(16, 12), seed=k)),
                          output=str(exr)))
    return items


def _sleeper(pid_file: str, done_file: str, seconds: float) -> None:
    """An item that says which process runs it, then works for a while and marks that it finished."""
    import os
    import time

    Path(pid_file).write_text(str(os.getpid()))
    time.sleep(seconds)
    Path(done_file).write_text("done")


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "State:\tZ" not in state  # a zombie has ended; only its exit status waits for a reaper


def _same(a: Path, b: Path) -> bool:
    files = sorted(p.name for p in a.glob("*.exr"))
    assert files == sorted(p.name for p in b.glob("*.exr")) and files
    for f in files:
        x, y = imageio.read_exr(a / f), imageio.read_exr(b / f)
        if sorted(x) != sorted(y) or any(not np.array_equal(x[c], y[c]) for c in x):
            return False
    return True


@pytest.mark.slow
def test_pool_and_ray_equal_serial_bit_for_bit(tmp_path):
    """Oracle: the serial run (this process, one Dr.Jit thread). Same items, same seeds, one thread per item:
    renders from two spawned workers and from two Ray workers must be identical to the last bit."""
    serial = run_items(_renders(tmp_path / "serial"), PoolSettings(workers=0, threads=1), show_progress=False)
    pool = run_items(_renders(tmp_path / "pool"), PoolSettings(workers=2, threads=1), show_progress=False)
    try:
        ray = run_items(_renders(tmp_path / "ray"), PoolSettings(workers=2, ray="local", threads=1),
                        show_progress=False)
    finally:
        ray_shutdown()
    for rep in (serial, pool, ray):
        assert not rep.failed and len(rep.ran) == 4, rep.summary()
    assert {r.where.split()[0] for r in pool.results} == {"pid"} and len({r.where for r in pool.results}) == 2
    assert all(r.where.startswith("ray ") for r in ray.results)
    assert _same(tmp_path / "serial", tmp_path / "pool") and _same(tmp_path / "serial", tmp_path / "ray")
    # the check can fail: another seed changes the bits
    other = _renders(tmp_path / "other")[:1]
    other = [Item(other[0].key, other[0].fn, (other[0].args[0], str(tmp_path / "other" / "0_material_test.exr"),
                                              RenderSettings(spp=4, resolution=(16, 12), seed=99)))]
    run_items(other, PoolSettings(workers=0, threads=1), show_progress=False)
    x = imageio.read_exr(tmp_path / "other" / "0_material_test.exr")
    y = imageio.read_exr(tmp_path / "serial" / "0_material_test.exr")
    assert not np.array_equal(x["R"], y["R"])


def test_failures_are_reported_the_rest_finish_and_reruns_resume(tmp_path):
    items = _renders(tmp_path / "out", ("material_test", "josie"))
    bad = tmp_path / "broken.xml"
    bad.write_text('<scene version="3.0.0"><shape type="sphere"><bsdf type="no_such_bsdf"/></shape></scene>')
    items.append(Item("broken", "foundation.scene:render_item",
                      (str(bad), str(tmp_path / "out" / "broken.exr"), RenderSettings(spp=1)),
                      output=str(tmp_path / "out" / "broken.exr")))
    items.append(Item("dies", "os:_exit", (3,)))  # takes its worker process down with it
    rep = run_items(items, PoolSettings(workers=2, threads=1, retries=1), show_progress=False)
    by = {r.key: r for r in rep.results}
    assert by["0_material_test"].ok and by["1_josie"].ok
    assert not by["broken"].ok and "broken.xml" in by["broken"].error and by["broken"].attempts == 2
    assert not by["dies"].ok and "worker process died" in by["dies"].error and by["dies"].attempts == 2
    assert "2 failed" in rep.summary() and "failed: broken:" in rep.summary()
    with pytest.raises(Exception, match="failed: broken"):
        rep.raise_if_failed()
    # rerun: what is done is skipped; a deleted output is made again
    (tmp_path / "out" / "1_josie.exr").unlink()
    again = run_items(items[:2], PoolSettings(workers=0, threads=1), show_progress=False)
    assert [r.skipped for r in again.results] == [True, False] and not again.failed
    # the same outputs asked for with other settings are not "done": they are made again
    other = [Item(it.key, it.fn, (it.args[0], it.args[1], RenderSettings(spp=2, resolution=(16, 12))),
                  output=it.output) for it in items[:2]]
    third = run_items(other, PoolSettings(workers=0, threads=1), show_progress=False)
    assert [r.skipped for r in third.results] == [False, False] and not third.failed


def test_cli_renders_many_scenes_and_names_a_bad_one(tmp_path, capsys):
    scenes = [str(SCENES / "material_test.xml"), str(SCENES / "josie.xml")]
    out = tmp_path / "renders"
    code = main(["render", *scenes, "--out-dir", str(out), "--spp", "2", "--resolution", "12", "8", "--workers", "0"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    summary = json.loads(cap.out)
    assert summary["done"] == 2 and summary["failed"] == [] and (out / "josie.exr").is_file()
    assert imageio.read_exr(out / "josie.exr")["R"].shape == (8, 12)
    code = main(["render", *scenes, "--out-dir", str(out), "--spp", "2", "--resolution", "12", "8", "--workers", "0"])
    assert code == 0 and json.loads(capsys.readouterr().out)["skipped"] == 2  # a rerun resumes
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0"><shape type="sphere"><bsdf type="no_such_bsdf"/></shape>'
                   '<sensor type="perspective"/></scene>')
    code = main(["render", scenes[0], str(bad), "--out-dir", str(tmp_path / "r2"), "--spp", "1", "--workers", "0"])
    cap = capsys.readouterr()
    assert code == 1 and "bad: SceneError" in cap.err and "no_such_bsdf" in cap.err
    assert (tmp_path / "r2" / "material_test.exr").is_file() and not (tmp_path / "r2" / "bad.exr").exists()
    code = main(["render", scenes[0], str(tmp_path / "nope.xml"), "--out-dir", str(tmp_path / "r3")])
    assert code == 2 and "nope.xml: scene file not found" in capsys.readouterr().err
    assert main(["render", *scenes, "-o", str(tmp_path / "x.exr")]) == 2
    assert "-o names one output" in capsys.readouterr().err


def test_a_worker_ends_when_its_driver_is_killed(tmp_path):
    """A killed driver must not leave workers finishing items into folders a rerun may own (seen 2026-11-27)."""
    import subprocess
    import sys
    import time

    pid_file, done_file = tmp_path / "pid", tmp_path / "done"
    code = ("from foundation.pool import Item, PoolSettings, run_items\n"
            f"run_items([Item('slow', 'tests.foundation.test_pool:_sleeper', ({str(pid_file)!r}, {str(done_file)!r}, 30.0))], "
            "PoolSettings(workers=1, threads=1), show_progress=False)\n")
    import os

    # the killed driver cannot remove its temporary folders: keep them under tmp_path
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    driver = subprocess.Popen([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[2], env=env)
    try:
        t0 = time.time()
        while not pid_file.exists() and time.time() - t0 < 120 and driver.poll() is None:
            time.sleep(0.1)
        assert pid_file.exists(), "the worker never started its item"
        worker = int(pid_file.read_text())
        assert _alive(worker)
    finally:
        driver.kill()  # SIGKILL: no cleanup in the driver at all
        driver.wait()
    t0 = time.time()
    while _alive(worker) and time.time() - t0 < 10:
        time.sleep(0.1)
    gone = not _alive(worker)
    if not gone:
        import signal

        os.kill(worker, signal.SIGKILL)
    assert gone, "the worker outlived its driver by 10 s"
    assert not done_file.exists()


@pytest.mark.slow
def test_ctrl_c_to_the_driver_stops_its_workers_at_once(tmp_path):
    """SIGINT to the driver alone (`kill -INT PID`, not the terminal's whole group) used to wait for the workers to
    finish their items (46 s for two renders): the workers are terminated, the driver exits 130 within seconds and
    the cut items leave no output."""
    import os
    import signal
    import subprocess
    import sys
    import time

    pids, dones = [tmp_path / f"pid{k}" for k in range(2)], [tmp_path / f"done{k}" for k in range(2)]
    items = ", ".join(f"Item('slow{k}', 'tests.foundation.test_pool:_sleeper', ({str(pids[k])!r}, {str(dones[k])!r}, "
                      "60.0))" for k in range(2))
    # the driver prints where its threads are if it has not exited 20 s after the signal (a failure says where)
    code = ("import faulthandler, signal, sys\nfrom foundation.pool import Item, PoolSettings, run_items\n"
            "signal.signal(signal.SIGINT, lambda *a: (faulthandler.dump_traceback_later(20), "
            "signal.default_int_handler(*a)))\n"
            f"try:\n    run_items([{items}], PoolSettings(workers=2, threads=1), show_progress=False)\n"
            "except KeyboardInterrupt:\n    sys.exit(130)\n")
    driver = subprocess.Popen([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[2],
                              env={**os.environ, "TMPDIR": str(tmp_path)}, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.time()
        while not all(p.exists() for p in pids) and time.time() - t0 < 120 and driver.poll() is None:
            time.sleep(0.1)
        assert all(p.exists() for p in pids), "the workers never started their items"
        workers = [int(p.read_text()) for p in pids]
        t0 = time.time()
        driver.send_signal(signal.SIGINT)
        try:
            err = driver.communicate(timeout=30)[1]
        except subprocess.TimeoutExpired:
            driver.kill()
            err = driver.communicate()[1]
        rc, seconds = driver.returncode, time.time() - t0
    finally:
        driver.kill()
    time.sleep(0.5)
    alive = [w for w in workers if _alive(w)]
    for w in alive:
        os.kill(w, signal.SIGKILL)
    assert rc == 130 and seconds < 10, (rc, seconds, err)
    assert not alive and not any(d.exists() for d in dones)
    assert "Traceback" not in err and "leaked" not in err, err  # e.g. the resource tracker's warning of semaphores


def test_an_unreachable_or_malformed_ray_address_fails_before_any_work(tmp_path, monkeypatch, capsys):
    """`--ray` is reached first, within a bound: one line naming the flag and the address, exit 2, nothing made.
    Oracle: a loopback port nothing listens on (refused at once), malformed addresses, and `auto` with no cluster."""
    import time

    import foundation.pool as pool
    from foundation.pool import PoolSettings

    for address, why in (("127.0.0.1:1", "cannot reach 127.0.0.1:1"), ("ray://127.0.0.1:1", "cannot reach"),
                         ("nonsense", "not 'local', 'auto' or HOST:PORT"), ("host:0", "HOST:PORT"),
                         ("host:99999", "HOST:PORT")):
        with pytest.raises(UsageError, match=f"--ray {re.escape(address)}: .*{re.escape(why)}"):
            PoolSettings(workers=1, ray=address)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setattr(pool, "_current_cluster", lambda: None)
    with pytest.raises(UsageError, match="--ray auto: no Ray cluster runs on this machine"):
        PoolSettings(workers=1, ray="auto")
    assert PoolSettings(workers=1, ray="local").ray == "local"  # starts Ray here: nothing to reach

    t = time.perf_counter()
    code = main(["render", str(SCENES / "material_test.xml"), "--out-dir", str(tmp_path / "d"), "--ray", "127.0.0.1:1"])
    err = capsys.readouterr().err
    assert code == 2 and time.perf_counter() - t < 10, (code, err)
    assert err.strip().splitlines() == ["photoreal: error: --ray 127.0.0.1:1: cannot reach 127.0.0.1:1 (Connection "
                                        "refused; waited at most 3 s)"]
    assert not (tmp_path / "d").exists()


def test_a_port_that_answers_but_is_no_ray_cluster_is_refused_within_the_bound(tmp_path, capsys):
    """A web server (or a proxy) at the address: Ray's own client retried for 20–40 s, a warning line a second."""
    import http.server
    import threading
    import time

    class Quiet(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):  # the test reads stderr
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    address = f"127.0.0.1:{server.server_address[1]}"
    try:
        t = time.perf_counter()
        code = main(["render", str(SCENES / "material_test.xml"), "--out-dir", str(tmp_path / "d"), "--ray", address])
        seconds = time.perf_counter() - t
    finally:
        server.shutdown()
    err = capsys.readouterr().err
    assert code == 2 and seconds < 10, (code, seconds, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and re.fullmatch(f"photoreal: error: --ray {re.escape(address)}: {re.escape(address)} "
                                            r"answers, but not as a Ray cluster \(no answer within [0-9.]+ s\)",
                                            lines[0]), err  # the bound less the connect's time
    assert not (tmp_path / "d").exists()

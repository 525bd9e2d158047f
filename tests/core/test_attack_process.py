"""The process under attack: a full disk, Ctrl-C at the worst moment, SIGKILL mid-write and
bad or dead Dask schedulers. Every output goes through riray.files (named error, previous
file kept, no partial or temporary file), Ctrl-C is one line and exit 130, and a bad
--scheduler is refused at once."""

import errno
import gc
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from riray import files
from riray.cli import main
from riray.imageio import write_float_image, write_png, write_png_u8
from riray.ritree import cache

SCRIPT = [sys.executable, "-m", "riray.cli"]
NO_PYC = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}


def _dev_full(monkeypatch):
    """Every atomic_write creates its temporary file as usual but writes into /dev/full, whose
    writes fail with ENOSPC: a full disk, reported by the kernel."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")

    def to_dev_full(tmp):
        open(tmp, "xb").close()
        return open("/dev/full", "wb")
    monkeypatch.setattr(files, "_open_temp", to_dev_full)


@pytest.fixture
def python_sigint():
    """SIGINT raises KeyboardInterrupt in this process during the test (a shell that started
    the suite in the background leaves it ignored)."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def _rays(path, n=40):
    rng = np.random.default_rng(3)
    o = np.array([0.0, -1.0, 0.9]) + rng.normal(0.0, 0.01, (n, 3))
    np.save(path, np.hstack([o, np.tile([0.0, 1.0, 0.0], (n, 1))]))
    return path


WRITERS = {
    "png": lambda p: write_png(p, np.full((4, 4, 3), 0.5)),
    "mask png": lambda p: write_png_u8(p, np.zeros((4, 4), np.uint8)),
    "npy": lambda p: write_float_image(p, np.ones((64, 64, 3))),
    "npz": lambda p: files.atomic_write(p, lambda f: np.savez_compressed(f, a=np.ones(5000))),
    "json": lambda p: files.atomic_write_text(p, json.dumps({"x": list(range(5000))})),
    "rit": lambda p: cache.save_tree(p, {"h": 1}, {"a": np.arange(5000)}),
}


@pytest.mark.parametrize("kind", WRITERS)
def test_disk_full_names_the_file_and_keeps_the_previous_one(kind, tmp_path, monkeypatch):
    path = tmp_path / f"out.{kind.split()[-1]}"
    path.write_bytes(b"previous")
    _dev_full(monkeypatch)
    with pytest.raises(files.WriteError) as e:
        WRITERS[kind](path)
    assert str(e.value) == f"cannot write {path}: No space left on device"
    assert e.value.errno == errno.ENOSPC
    assert path.read_bytes() == b"previous"
    assert os.listdir(tmp_path) == [path.name]


def test_trace_rays_disk_full_is_one_line_without_zipfile_noise(tmp_path, monkeypatch, capsys):
    """numpy.savez's ZipFile, left behind by the failed write, closes from its destructor
    without a word ("Exception ignored in ZipFile.__del__" before)."""
    rays = _rays(tmp_path / "rays.npy")
    out = tmp_path / "f.npz"
    out.write_bytes(b"previous")
    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    _dev_full(monkeypatch)
    rc = main(["trace-rays", "glass_sphere", "--rays", str(rays), "--out", str(out), "--quiet",
               "--workers", "1"])
    gc.collect()
    err = capsys.readouterr().err
    assert rc == 2
    assert err == f"riray trace-rays: error: cannot write {out}: No space left on device\n"
    assert unraisable == []
    assert out.read_bytes() == b"previous"
    assert sorted(os.listdir(tmp_path)) == ["f.npz", "rays.npy"]


def _limited(limit_bytes):
    """preexec_fn: files this process writes may not grow past ``limit_bytes`` (the kernel
    fails the write with EFBIG; Python ignores SIGXFSZ)."""
    def set_limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return set_limit


@pytest.mark.skipif(not hasattr(resource, "RLIMIT_FSIZE"), reason="no RLIMIT_FSIZE")
def test_cli_write_failures_are_one_line_and_change_no_file(tmp_path):
    """A real failing write() (the file size limit): trace-rays and render say which file and
    why, in one line with exit 2; render's PNG, .npy and .json change together or not at all
    (the .npy fails here after the PNG was written, and the old PNG stays)."""
    rays = _rays(tmp_path / "rays.npy", n=3000)
    npz = tmp_path / "f.npz"
    npz.write_bytes(b"previous")
    run = subprocess.run(SCRIPT + ["trace-rays", "glass_sphere", "--rays", str(rays), "--out",
                                   str(npz), "--quiet", "--workers", "1"], env=NO_PYC,
                         capture_output=True, text=True, timeout=120,
                         preexec_fn=_limited(20_000))
    assert run.returncode == 2, run.stderr
    assert run.stderr == f"riray trace-rays: error: cannot write {npz}: File too large\n"
    assert npz.read_bytes() == b"previous"
    for name in ("img.png", "img.json"):
        (tmp_path / name).write_bytes(b"previous")
    run = subprocess.run(SCRIPT + ["render", "glass_sphere", "--width", "64", "--height", "64",
                                   "--out", str(tmp_path / "img"), "--quiet", "--workers", "1"],
                         env=NO_PYC, capture_output=True, text=True, timeout=120,
                         preexec_fn=_limited(40_000))
    assert run.returncode == 2, run.stderr
    assert run.stderr == (f"riray render: error: cannot write {tmp_path / 'img.npy'}: "
                          "File too large\n")
    assert (tmp_path / "img.png").read_bytes() == b"previous"
    assert (tmp_path / "img.json").read_bytes() == b"previous"
    assert sorted(os.listdir(tmp_path)) == ["f.npz", "img.json", "img.png", "rays.npy"]


# --------------------------------------------------------------------------- Ctrl-C at commit
def _sigint_inside(monkeypatch, name, after=True):
    """os.<name> does its work and then (``after``) or first gets a Ctrl-C: a SIGINT sent to
    this process, which Python acts on at the next bytecode."""
    real = getattr(os, name)

    def hit(*args):
        if not after:
            signal.raise_signal(signal.SIGINT)
        out = real(*args)
        if after:
            signal.raise_signal(signal.SIGINT)
        return out
    monkeypatch.setattr(os, name, hit)


def test_ctrl_c_during_the_rename_is_held_back_and_keeps_the_new_file(tmp_path, monkeypatch,
                                                                      python_sigint):
    """The rename happens whole and the temporary file, now the target, is not removed
    (before: "No such file or directory: ...tmp" although the save had succeeded); the
    Ctrl-C is raised after it."""
    path = tmp_path / "t.rit"
    cache.save_tree(path, {"old": True}, {"a": np.zeros(3)})
    _sigint_inside(monkeypatch, "replace")
    with pytest.raises(KeyboardInterrupt):
        cache.save_tree(path, {"new": True}, {"a": np.ones(3)})
    monkeypatch.undo()
    assert cache.load_tree(path)[0] == {"new": True}
    assert os.listdir(tmp_path) == ["t.rit"]


def test_cli_ctrl_c_at_the_rename_still_prints_the_whole_report(tmp_path, monkeypatch, capsys,
                                                               python_sigint):
    """From the rename on, the command's Ctrl-C is ignored: the new file is in place and the
    report is printed, exit 0 (before: "interrupted", exit 130, with the new file in place).
    Called in-process, main puts the SIGINT handler back."""
    rays, out = _rays(tmp_path / "rays.npy"), tmp_path / "f.npz"
    _sigint_inside(monkeypatch, "replace")
    rc = main(["trace-rays", "glass_sphere", "--rays", str(rays), "--out", str(out), "--quiet",
               "--workers", "1"])
    monkeypatch.undo()
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert captured.out == f"{out}: 40 rays, 40 hit the object, 0 null\n"
    assert np.load(out)["hit"].all()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_cli_ctrl_c_before_the_rename_keeps_the_previous_file(tmp_path, monkeypatch, capsys,
                                                             python_sigint):
    rays, out = _rays(tmp_path / "rays.npy"), tmp_path / "f.npz"
    out.write_bytes(b"previous")
    _sigint_inside(monkeypatch, "fsync")
    rc = main(["trace-rays", "glass_sphere", "--rays", str(rays), "--out", str(out), "--quiet",
               "--workers", "1"])
    monkeypatch.undo()
    captured = capsys.readouterr()
    assert rc == 130 and captured.err == "riray trace-rays: interrupted\n" and captured.out == ""
    assert out.read_bytes() == b"previous"
    assert sorted(os.listdir(tmp_path)) == ["f.npz", "rays.npy"]


# --------------------------------------------------------------------------- stale temp files
def _temp(path, pid, host=None, age_s=0.0):
    host = host or files._host_tag()
    t = Path(f"{path}.{pid}-{host}.{os.urandom(6).hex()}.tmp")
    t.write_bytes(b"partial")
    if age_s:
        then = time.time() - age_s
        os.utime(t, (then, then))
    return t


def _dead_pid():
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_next_write_removes_only_abandoned_temp_files(tmp_path):
    """Of the target's temporary files, a dead writer's (this host) and any writer's idle for
    longer than STALE_TMP_S go; a live writer's (a concurrent bake of the same file) and
    another host's recent one stay, as do other targets' and other files."""
    path = tmp_path / "t.rit"
    old = files.STALE_TMP_S + 60
    dead = _temp(path, _dead_pid())
    live = _temp(path, os.getppid())
    live_idle = _temp(path, os.getppid(), age_s=old)
    remote = _temp(path, _dead_pid(), host="0badc0de")
    remote_idle = _temp(path, 1, host="0badc0de", age_s=old)
    other_target = _temp(tmp_path / "u.rit", _dead_pid())
    other = tmp_path / "t.rit.notes.tmp"
    other.write_bytes(b"mine")
    files.atomic_write_text(path, "new")
    assert path.read_text() == "new"
    left = set(os.listdir(tmp_path))
    assert left == {p.name for p in (path, live, remote, other_target, other)}
    assert not {dead.name, live_idle.name, remote_idle.name} & left


def test_sigkill_mid_write_leaves_a_temp_file_the_next_write_removes(tmp_path):
    path = tmp_path / "t.rit"
    code = ("import sys, time\nfrom riray import files\n"
            "def write(f):\n    f.write(b'x' * 100000); f.flush(); print('writing', flush=True)"
            "\n    time.sleep(60)\n"
            f"files.atomic_write({str(path)!r}, write)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline() == "writing\n"
    finally:
        proc.kill()
        proc.wait(timeout=30)
    left = os.listdir(tmp_path)
    assert len(left) == 1 and files.temp_pattern(path).fullmatch(left[0])
    cache.save_tree(path, {"h": 1}, {"a": np.arange(3)})
    assert os.listdir(tmp_path) == ["t.rit"]


# --------------------------------------------------------------------------- Dask scheduler
@pytest.fixture
def dask_cluster_module():
    pytest.importorskip("distributed")
    from riray import cluster
    return cluster


def test_local_worker_count_is_capped_before_anything_starts(dask_cluster_module, monkeypatch,
                                                             capsys, tmp_path):
    """local:100000 started processes until memory ran out; now exit 2 at once, naming the
    limit."""
    import distributed
    monkeypatch.setattr(distributed, "LocalCluster",
                        lambda *a, **k: pytest.fail("started a LocalCluster"))
    cap = dask_cluster_module.max_local_workers()
    assert cap == dask_cluster_module.LOCAL_WORKERS_PER_CORE * (os.cpu_count() or 1)
    rc = main(["bake", "glass_sphere", "--scheduler", "local:100000", "--out",
               str(tmp_path / "t.rit")])
    assert rc == 2
    assert capsys.readouterr().err == (
        f"riray bake: error: --scheduler local:100000: at most {cap} worker processes on this "
        f"machine (riray.cluster.LOCAL_WORKERS_PER_CORE: "
        f"{dask_cluster_module.LOCAL_WORKERS_PER_CORE} per CPU core)\n")


def _free_loopback_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_refused_scheduler_address_fails_at_once(dask_cluster_module):
    """Nothing listens: the connection is refused at once, and so is the bake (before: after
    Dask's 30 s connect timeout)."""
    addr = f"tcp://127.0.0.1:{_free_loopback_port()}"
    t0 = time.monotonic()
    with pytest.raises(dask_cluster_module.ClusterError,
                       match=f"Dask scheduler {addr}: cannot connect \\(Connection refused\\)"):
        dask_cluster_module.connect(addr)
    assert time.monotonic() - t0 < 10


def test_a_silent_listener_fails_after_the_connect_timeout(dask_cluster_module):
    """Something takes the connection but never speaks (a wrong port, the dashboard's): Dask's
    client would wait for its handshake forever; the bake fails after Dask's connect timeout."""
    import dask
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(8)
        addr = f"tcp://127.0.0.1:{s.getsockname()[1]}"
        t0 = time.monotonic()
        with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
            with pytest.raises(dask_cluster_module.ClusterError,
                               match=f"Dask scheduler {addr}: no answer within 1 s"):
                dask_cluster_module.connect(addr)
        assert time.monotonic() - t0 < 20


def _sigint_blocked(pid):
    """Whether SIGINT is blocked in every thread of process ``pid`` (Linux /proc)."""
    masks = []
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/status") as f:
                masks += [int(line.split()[1], 16) for line in f if line.startswith("SigBlk:")]
        except FileNotFoundError:  # the thread ended between listing and reading
            continue
    assert masks, f"no thread of process {pid} could be read"
    return all(m & (1 << (signal.SIGINT - 1)) for m in masks)


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")
def test_local_cluster_workers_never_see_a_ctrl_c(dask_cluster_module):
    """The terminal's Ctrl-C reaches the whole process group; the local:N worker processes
    block SIGINT in every thread, so only this process acts on it (before, each worker
    printed its own KeyboardInterrupt tracebacks)."""
    with dask_cluster_module.connect("local:1") as c:
        pids = list(c.client.run(os.getpid).values())
        assert pids and all(_sigint_blocked(pid) for pid in pids)
    assert not _sigint_blocked(os.getpid())


def _group_alive(pgid):
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="needs process groups")
def test_ctrl_c_to_the_process_group_of_a_local_cluster_bake(dask_cluster_module, tmp_path,
                                                             default_sigint):
    """Ctrl-C at a terminal: SIGINT to the bake's whole process group mid-bake. One line,
    exit 130, the previous cache byte for byte, and no process of the group left."""
    out = tmp_path / "a.rit"
    out.write_bytes(b"previous cache")
    proc = subprocess.Popen(SCRIPT + ["bake", "glass_sphere", "--cameras", "close",
                                      "--viewpoint-depth", "2", "--direction-depth", "3",
                                      "--scheduler", "local:2", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            process_group=0, preexec_fn=default_sigint)
    try:
        seen, t0 = "", time.monotonic()
        while "bake:" not in seen and time.monotonic() - t0 < 120:     # shards are running
            c = proc.stderr.read(1)
            if not c:
                break
            seen += c
        assert seen.startswith("dask: scheduler tcp://127.0.0.1:"), seen
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
        deadline = time.monotonic() + 30
        while _group_alive(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not _group_alive(proc.pid)
    finally:
        if _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.kill()
        proc.wait()
    assert proc.returncode == 130, err
    lines = [ln for ln in err.replace("\r", "\n").splitlines()
             if ln.strip() and not ln.startswith(("bake:", "save"))]
    assert lines == ["riray bake: interrupted"], err
    assert out.read_bytes() == b"previous cache"
    assert os.listdir(tmp_path) == ["a.rit"]

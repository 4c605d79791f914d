"""`gpnarx --version` and the CLI's exit codes: 1 for a runtime error, 2 for a usage error."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import gpnarx
from gpnarx.cli.errors import CLIError, UsageError
from gpnarx.cli.main import main


def test_version_prints_the_package_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"gpnarx {gpnarx.__version__}"


def test_version_from_the_console_entry_point():
    r = subprocess.run([sys.executable, "-m", "gpnarx", "--version"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == f"gpnarx {gpnarx.__version__}", r


def test_error_types_carry_their_codes():
    assert CLIError("x").exit_code == 1 and UsageError("x").exit_code == 2
    assert issubclass(UsageError, CLIError)


@pytest.fixture()
def registry(tmp_path):
    reg = tmp_path / "reg"
    reg.mkdir()
    rec = tmp_path / "r.npz"
    np.savez(rec, u=np.zeros(32), fs=750.0)
    return reg, rec


@pytest.mark.parametrize("argv, needle, code", [
    (["predict", "--registry", "{reg}", "--model", "nosuch", "{rec}"], "not found", 1),  # unknown model
    (["novelty", "--registry", "{reg}", "--model", "nosuch", "{rec}"], "not found", 1),
    (["predict", "--registry", "{reg}/absent", "--model", "m", "{rec}"], "does not exist", 1),
    (["predict", "--registry", "{reg}", "--model", "../x", "{rec}"], "invalid", 2),  # bad model name syntax
    (["predict", "--registry", "{reg}", "--model", "m"], "required", 2),  # missing RECORD
    (["predict", "--registry", "{reg}", "--model", "m", "{rec}", "--no-such-option"], "--no-such-option", 2),
    (["no-such-command"], "no-such-command", 2),
    (["predict", "--registry", "{reg}", "--model", "m", "{rec}", "--out", "{tmp}/pred.xyz"], "--out", 2),  # no format
    (["predict", "--registry", "{reg}", "--model", "m", "{rec}", "--out", "{tmp}"], "--out", 2),  # a directory
    (["predict", "--registry", "{reg}", "--model", "m", "{rec}", "--out", "{tmp}/absent/p.npz"], "--out", 2),
    (["simulate", "bouc-wen", "--amplitude", "-1", "--out", "{tmp}/o.npz"], "--amplitude", 2),
    (["simulate", "bouc-wen", "--amplitude", "1", "--out", "{tmp}/absent/o.npz"], "does not exist", 1),
    (["calibrate", "--registry", "{reg}", "--model", "m", "{rec}", "{rec}", "--false-alarm-rate", "0.9"],
     "--false-alarm-rate", 2),
])
def test_exit_codes(argv, needle, code, registry, tmp_path, capsys):
    reg, rec = registry
    rc = main([a.format(reg=reg, rec=rec, tmp=tmp_path) for a in argv])
    err = capsys.readouterr().err
    assert rc == code, err
    assert needle in err and len(err.strip().splitlines()) == 1, err


def test_unreadable_record_is_a_runtime_error(tmp_path, capsys):
    from conftest import sdof_simulate

    from gpnarx.model.estimator import GPNARX
    from gpnarx.storage.bundle import save_bundle

    rng = np.random.default_rng(0)
    u = rng.standard_normal(300)
    model = GPNARX(ny=2, nu=2, max_train_points=120, n_restarts=0).fit([(u, sdof_simulate(u))])
    reg = tmp_path / "reg"
    save_bundle(model, reg, "m", fs=500.0, units={"u": "N", "y": "m"})
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip archive")
    rc = main(["predict", "--registry", str(reg), "--model", "m", str(bad)])
    err = capsys.readouterr().err
    assert rc == 1 and "bad.npz" in err and len(err.strip().splitlines()) == 1, err
    good = tmp_path / "good.npz"
    np.savez(good, u=u[:50], fs=500.0)
    assert main(["predict", "--registry", str(reg), "--model", "m", str(good), "--mc", "0"]) == 2  # usage
    assert main(["predict", "--registry", str(reg), "--model", "m", str(good), "--mc", "4"]) == 0


_SPINNING_COMMAND = '''
import sys, time, types
from joblib import Parallel, delayed
import gpnarx.cli.main as M

def spin(i):
    t = time.time()
    while time.time() - t < 120:
        pass
    return i

def add_parser(sub):
    p = sub.add_parser("spin")
    p.set_defaults(func=lambda a: {"done": list(Parallel(n_jobs=2, return_as="generator")(
        delayed(spin)(i) for i in range(4)))})

mod = types.ModuleType("spin_command")
mod.add_parser = add_parser
sys.modules["spin_command"] = mod
M.COMMAND_MODULES.append("spin_command")
sys.argv = ["gpnarx", "spin"]
sys.exit(M.main())  # as the console script calls it: the process's entry point
'''


def _children(pid: int) -> set[int]:
    """Live processes whose parent is ``pid`` (Linux /proc), zombies left out."""
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.add(int(stat.parent.name))
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigterm_ends_a_command_and_its_worker_processes():
    """SIGTERM (a scheduler stopping a job) ends a command with exit code 143 and one line on stderr, and the
    joblib workers it started end with it instead of computing their current task on (the default SIGTERM
    death left them running)."""
    import contextlib
    import os
    import signal
    import tempfile
    import time

    workers: set[int] = set()
    with tempfile.TemporaryFile("w+") as errfile:  # a file, not a pipe: workers left running would hold a pipe open
        proc = subprocess.Popen([sys.executable, "-c", _SPINNING_COMMAND], stderr=errfile, text=True)
        try:
            deadline = time.time() + 120
            while time.time() < deadline:  # both loky workers up (resource trackers are children too)
                workers = {c for c in _children(proc.pid) if b"popen_loky" in _cmdline(c)}
                if len(workers) >= 2:
                    break
                time.sleep(0.2)
            assert len(workers) >= 2, "the command's worker processes did not start"
            time.sleep(1.0)  # the workers are inside their 120 s tasks
            os.kill(proc.pid, signal.SIGTERM)
            rc = proc.wait(timeout=60)
            deadline = time.time() + 30
            while time.time() < deadline and any(_alive(w) for w in workers):
                time.sleep(0.2)
            left = [w for w in workers if _alive(w)]
        finally:
            if proc.poll() is None:
                proc.kill()
            for w in workers:  # never leave a spinning worker behind, whatever the outcome
                with contextlib.suppress(OSError):
                    os.kill(w, signal.SIGKILL)
        errfile.seek(0)
        err = errfile.read()
    assert rc == 143 and "gpnarx: terminated" in err and "Traceback" not in err, (rc, err[-2000:])
    assert not left, "worker processes still running after SIGTERM"


def test_main_called_in_process_leaves_the_process_sigterm_alone(monkeypatch):
    """main([...]) called by a program or a test is not the process's entry point: during its command SIGTERM
    keeps the handler the process had (a scheduler's SIGTERM still ends the whole process, not one call)."""
    import signal
    import types

    import gpnarx.cli.main as M

    seen = []

    def add_parser(sub):
        sub.add_parser("probe-signal").set_defaults(func=lambda a: seen.append(signal.getsignal(signal.SIGTERM)))

    monkeypatch.setitem(sys.modules, "probe_signal_command", types.SimpleNamespace(add_parser=add_parser))
    monkeypatch.setattr(M, "COMMAND_MODULES", [*M.COMMAND_MODULES, "probe_signal_command"])
    before = signal.getsignal(signal.SIGTERM)
    assert M.main(["probe-signal"]) == 0
    assert seen == [before] and signal.getsignal(signal.SIGTERM) is before


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_negative_seed_names_the_option(tmp_path, capsys):
    """The seed is checked with the other request fields (operations.plan), so the CLI names --seed."""
    from test_service_support import built_registry

    rec = tmp_path / "r.npz"
    np.savez(rec, u=np.sin(np.arange(256) * 0.3), fs=750.0)
    rc = main(["predict", "--registry", str(built_registry().root), "--model", "boucwen", str(rec), "--method", "mc",
               "--mc", "8", "--seed", "-1"])
    err = capsys.readouterr().err
    assert rc == 2 and "--seed" in err and len(err.strip().splitlines()) == 1, err

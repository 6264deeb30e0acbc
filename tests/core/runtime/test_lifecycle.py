"""A daemon asked to stop stops: a stop stuck past its limit (in the shutdown, or before it in the
main loop) dumps every thread's stack and exits with ``ExitCode.FAILURE``; one that finishes in
time exits normally, with no dump."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import pytest

from zoffload.runtime.errors import ExitCode
from zoffload.runtime.lifecycle import StopSignal

# A daemon's shape in a few lines: install the signals, wait for one, shut down. Its shutdown takes
# ``argv[1]`` s, its main loop ``argv[2]`` s more after the signal; *fake* hangs (sleeps): the real
# one seen once in CI could not be caused at will.
DAEMON = textwrap.dedent("""
    import sys, time
    from zoffload.runtime.lifecycle import StopSignal

    def stuck_in_shutdown(seconds):
        time.sleep(seconds)

    def stuck_in_main_loop(seconds):
        time.sleep(seconds)

    stop = StopSignal(shutdown_limit=1.0).install()
    print("up", flush=True)
    stop.wait(30)
    stuck_in_main_loop(float(sys.argv[2]))
    with stop.bounded_shutdown():
        stuck_in_shutdown(float(sys.argv[1]))
    print("stopped", flush=True)
""")


def _daemon(shutdown: float, main_loop: float = 0.0) -> tuple[int, str, str, float]:
    p = subprocess.Popen([sys.executable, "-c", DAEMON, str(shutdown), str(main_loop)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert p.stdout is not None and p.stdout.readline() == "up\n"
        t0 = time.monotonic()
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=20)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    return p.returncode, out, err, time.monotonic() - t0


def test_a_shutdown_stuck_past_its_limit_dumps_the_stacks_and_exits() -> None:
    code, out, err, took = _daemon(shutdown=60)
    assert code == ExitCode.FAILURE, (code, err)
    assert took < 10, took  # the 1 s limit, not the 60 s hang
    assert "stopped" not in out
    assert "Timeout" in err and "stuck_in_shutdown" in err, err  # where it was stuck


def test_a_main_loop_stuck_after_the_signal_is_bounded_too() -> None:
    code, out, err, took = _daemon(shutdown=0.0, main_loop=60)
    assert code == ExitCode.FAILURE and took < 10, (code, took, err)
    assert "stuck_in_main_loop" in err and "stopped" not in out, err


def test_a_shutdown_within_its_limit_exits_normally_without_a_dump() -> None:
    code, out, err, _ = _daemon(shutdown=0.2)
    assert code == ExitCode.OK and "stopped" in out, err
    assert "Timeout" not in err and "stuck_in_shutdown" not in err, err


def test_the_limit_comes_from_the_environment_when_it_is_a_positive_number(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from zoffload.runtime.lifecycle import SHUTDOWN_LIMIT

    for raw, limit in (("20", 20.0), ("2.5", 2.5), ("0", SHUTDOWN_LIMIT), ("-1", SHUTDOWN_LIMIT),
                       ("soon", SHUTDOWN_LIMIT), ("inf", SHUTDOWN_LIMIT), ("", SHUTDOWN_LIMIT)):
        monkeypatch.setenv("ZOFFLOAD_SHUTDOWN_LIMIT", raw)
        assert StopSignal().shutdown_limit == limit, raw


def test_a_stop_signal_it_did_not_install_bounds_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    """In-process servers (tests, the Python API) leave the process's faulthandler alone."""
    armed: list[float] = []
    monkeypatch.setattr("faulthandler.dump_traceback_later", lambda t, **kw: armed.append(t))
    with StopSignal(shutdown_limit=0.01).bounded_shutdown():
        pass
    assert armed == []


# The signal lands on another thread (as it may on any of Zenoh's), the main thread waits for the
# stop with no timeout; a watchdog ends the wait after 10 s whatever happens.
OTHER_THREAD = textwrap.dedent("""
    import signal, threading, time
    from zoffload.runtime.lifecycle import StopSignal

    stop = StopSignal().install()

    def raise_here():
        time.sleep(0.3)
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # delivered to this thread

    threading.Thread(target=raise_here, daemon=True).start()
    watchdog = threading.Timer(10.0, stop.event.set)
    watchdog.daemon = True  # the process ends with its wait, not 10 s later
    watchdog.start()
    t0 = time.monotonic()
    stop.wait()
    print(f"{time.monotonic() - t0:.2f} {stop._count}", flush=True)
""")


def test_a_signal_handled_on_another_thread_ends_a_wait_without_a_timeout() -> None:
    """Was: ``zoffload router`` waited for its stop with no timeout, and a SIGINT the kernel gave
    one of Zenoh's threads only set Python's flag: the main thread never woke to run the handler
    (no "SIGINT received" in its log) until a test killed it 30 s later."""
    out = subprocess.run([sys.executable, "-c", OTHER_THREAD], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    waited, handled = out.stdout.split()
    assert handled == "1" and float(waited) < 3.0, out.stdout  # the handler ran: not the watchdog

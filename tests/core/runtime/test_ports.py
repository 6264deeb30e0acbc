"""Free ports for local runs and tests: below the kernel's ephemeral range, so that no outgoing
connection can take one between the moment it is picked and the moment its server listens."""

from __future__ import annotations

import socket

from zoffload.runtime.session import ephemeral_ports, free_tcp_port


def test_free_ports_are_below_the_ephemeral_range_and_bindable() -> None:
    low, high = ephemeral_ports()
    assert 1024 <= low <= high <= 65535
    ports = {free_tcp_port() for _ in range(20)}
    assert len(ports) > 1  # picked at random, not the kernel's next one
    for port in ports:
        if low > 21000:
            assert 20000 <= port < low
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", port))  # free when picked (nothing else here takes it)


def test_a_port_in_use_is_never_picked() -> None:
    held = []
    try:
        for _ in range(200):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", free_tcp_port()))
            held.append(s)
        taken = {s.getsockname()[1] for s in held}
        assert len(taken) == 200  # every bind succeeded: no port picked twice while held
    finally:
        for s in held:
            s.close()

"""The weights benchmark's egress counter: bytes acknowledged on this process's TCP sockets (`ss -ti`)."""

from __future__ import annotations

import os
import shutil
import socket
import time

import pytest

from romannet.bench.weights_latency import bytes_out


@pytest.mark.skipif(shutil.which("ss") is None, reason="needs iproute2's ss")
def test_bytes_out_counts_what_this_process_sent() -> None:
    with socket.create_server(("127.0.0.1", 0)) as server:
        client = socket.create_connection(server.getsockname())
        peer, _ = server.accept()
        with client, peer:
            before = bytes_out(os.getpid())
            client.sendall(b"\x01" * 1_000_000)
            got = 0
            while got < 1_000_000:
                got += len(peer.recv(1 << 20))
            time.sleep(0.2)  # the last ack
            after = bytes_out(os.getpid())
    assert before is not None and after is not None
    assert 1_000_000 <= after - before < 1_100_000
    assert bytes_out(-1) == 0  # no socket of a process that does not exist

"""The estimated wrench for other programs: `run --publish HOST:PORT` sends each control step as a UDP JSON datagram."""

from __future__ import annotations

import json
import math
import socket

import pytest

from cell.view.publish import WrenchPublisher, parse_endpoint
from drivers.errors import ConfigError
from main import main


@pytest.fixture
def listener():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)  # a whole run's datagrams wait here
    sock.settimeout(0.5)
    yield sock
    sock.close()


def drain(sock: socket.socket) -> list[dict]:
    out = []
    try:
        while True:
            out.append(json.loads(sock.recv(65536)))
    except TimeoutError:
        return out


def test_publisher_sends_the_row_as_json_and_a_missing_reading_as_null(listener):
    pub = WrenchPublisher(listener.getsockname(), joints=2)
    row = {"t": 0.008, "cycle": 1, "state": "wipe", "q1": 0.1, "q2": 0.2,
           "fx": 1.0, "fy": 2.0, "fz": float("nan"), "mx": 0.1, "my": 0.2, "mz": 0.3}
    pub.row(row)
    pub.event("outcome: done")
    pub.close()
    msg, end = drain(listener)
    assert msg == {"t": 0.008, "cycle": 1, "state": "wipe", "wrench": [1.0, 2.0, None, 0.1, 0.2, 0.3],
                   "sensor": None, "q": [0.1, 0.2]}
    assert end == {"event": "outcome: done"}


def test_publisher_without_a_reader_drops_and_goes_on():
    pub = WrenchPublisher(("127.0.0.1", 9), joints=0)  # the discard port: nobody listens
    for k in range(5):
        pub.row({"t": k * 0.008, "cycle": k, "fx": 0, "fy": 0, "fz": 0, "mx": 0, "my": 0, "mz": 0})
    assert pub.sent + pub.dropped == 5
    pub.close()


@pytest.mark.parametrize("bad", ["nohost", "host:", "h:0", "h:70000", "h:12x"])
def test_a_bad_endpoint_is_refused(bad):
    with pytest.raises(ConfigError, match="HOST:PORT"):
        parse_endpoint(bad)


def test_run_publishes_every_step(listener, capsys):
    port = listener.getsockname()[1]
    code = main(["-q", "run", "wipe", "--force-source", "sensor", "--no-record", "--json",
                 "--publish", f"127.0.0.1:{port}"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0
    msgs = drain(listener)
    steps = [m for m in msgs if "wrench" in m]
    assert len(steps) == summary["cycles"] + 1  # as the log: every step, the finishing one too
    assert msgs[-1] == {"event": "outcome: done"}
    wiping = [m["wrench"][2] for m in steps if m["state"] == "wipe"]
    assert wiping and math.isclose(sum(wiping) / len(wiping), 60.0, abs_tol=3.0)  # the 60 N it regulated

"""Rows over UDP (visvec.sinks): one datagram per row, bad addresses refused."""

import json

import pytest

from conftest import CONFIGS, SAMPLES, rows_of, run

RIG = str(CONFIGS / "triangle.toml")


@pytest.mark.parametrize("fmt", ["csv", "jsonl"])
def test_rows_stream_to_udp_one_datagram_each(fmt):
    """--out udp://HOST:PORT: every row is one datagram (a CSV header first), in order,
    for a flight computer or ground station listening on a socket."""
    import socket

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(5.0)
    url = f"udp://127.0.0.1:{rx.getsockname()[1]}"
    try:
        r = run("batch", SAMPLES, "--rig", RIG, "--out", url, "--format", fmt, "--max-frames", "3")
        assert r.exit_code == 0, r.output
        got = [rx.recv(65536).decode() for _ in range(4 if fmt == "csv" else 3)]
    finally:
        rx.close()
    assert all(g.endswith("\n") and g.count("\n") == 1 for g in got)
    rows = rows_of("".join(got)) if fmt == "csv" else [json.loads(g) for g in got]
    assert [int(x["frame"]) for x in rows] == [0, 1, 2]
    assert all(x["status"] == "ok" for x in rows)
    assert r.stdout == ""  # nothing on stdout when the rows go to the socket


@pytest.mark.parametrize(
    "url, words",
    [
        ("udp://127.0.0.1", "expected udp://HOST:PORT"),
        ("udp://no-such-host.invalid:5005", "cannot resolve"),
    ],
)
def test_bad_udp_address_is_refused_before_any_row(url, words):
    r = run("batch", SAMPLES, "--rig", RIG, "--out", url)
    assert r.exit_code == 2 and words in r.output

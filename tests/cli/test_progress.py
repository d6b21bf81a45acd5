"""Progress and status lines (visvec.cli.progress) and rows streamed, not held."""

import cv2
import pytest
from click.testing import CliRunner

from visvec.cli.frames import run_frames
from visvec.cli.main import cli
from visvec.data import Frame
from visvec.errors import NoOkRows
from visvec.rig import load_rig

from conftest import CONFIGS, SAMPLES, rows_of

RIG = str(CONFIGS / "triangle.toml")


def test_status_lines_for_an_operator(tmp_path, capsys):
    """With the rows going to a file, `track` at a terminal prints a status line every
    few seconds and one at the end: frames, ok share, rate, the last ok attitude."""
    rig = load_rig(RIG)
    imgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(SAMPLES.glob("*.png"))[:3]]
    frames = [Frame(i, i / 30, im, f"f{i}") for i, im in enumerate(imgs)]
    frames.append(Frame(3, 0.1, None, "f3", error="empty frame"))
    out = tmp_path / "rows.csv"
    run_frames(
        rig,
        frames,
        out=str(out),
        fmt="csv",
        method=None,
        overlay=None,
        max_frames=None,
        progress=1e-9,  # a status line after every frame (stderr is not a terminal here)
    )
    lines = [x for x in capsys.readouterr().err.splitlines() if "frames/s" in x]
    assert len(lines) == 5  # one per frame at a 0 s interval, and the last
    assert lines[-1].startswith("visvec: 4 frames, 3 ok (75.0 %),")
    last = rows_of(out.read_text())[2]
    assert f"last ok (frame 2): yaw {float(last['yaw_deg']):+.4f}, pitch" in lines[-1]
    # and why the others were not ok
    assert lines[-1].endswith("; not ok: read_error 1") and "not ok" not in lines[0]


def test_a_long_run_does_not_hold_its_rows_in_memory(tmp_path):
    """`track` can run for hours: the loop's memory must not grow with the frame count."""
    import tracemalloc

    rig = load_rig(RIG)

    def peak(n):
        frames = (Frame(i, i / 30, None, f"f{i}", error="empty frame") for i in range(n))
        tracemalloc.start()
        with pytest.raises(NoOkRows):  # every frame here is a read_error: exit 4
            run_frames(
                rig,
                frames,
                out=str(tmp_path / "r.csv"),
                fmt="csv",
                method=None,
                overlay=None,
                max_frames=None,
            )
        size = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return size

    assert peak(4000) - peak(400) < 100_000  # bytes; a kept row is about 1 kB


def test_status_lines_when_stderr_is_not_a_terminal(tmp_path):
    """Long work says it is alive: status lines every --status-every seconds (none with
    0), and every batch ends with its one-line summary."""
    runner = CliRunner()
    r = runner.invoke(cli, ["--status-every", "0.001", "batch", str(SAMPLES), "--rig", str(RIG),
                            "--out", str(tmp_path / "a.csv")])  # fmt: skip
    assert r.exit_code == 0, r.output
    lines = [x for x in r.stderr.splitlines() if x.startswith("visvec: batch: ")]
    assert lines and all(" of 12 frames (" in x and "ok " in x for x in lines)
    assert r.stderr.splitlines()[-1].startswith("visvec: 12 frames, 12 ok (100.0 %)")
    r = runner.invoke(cli, ["--status-every", "0", "batch", str(SAMPLES), "--rig", str(RIG),
                            "--out", str(tmp_path / "b.csv")])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert not [x for x in r.stderr.splitlines() if x.startswith("visvec: batch: ")]
    assert "visvec: 12 frames, 12 ok" in r.stderr


def test_progress_bar_at_a_terminal(tmp_path):
    """At a terminal, a bar (with the frame count and the ok share) instead of lines."""
    import fcntl
    import os
    import pty
    import struct
    import subprocess
    import sys
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    proc = subprocess.Popen(
        [sys.executable, "-m", "visvec", "batch", str(SAMPLES), "--rig", str(RIG), "--out",
         str(tmp_path / "rows.csv")],
        stderr=slave, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    os.close(slave)
    out = b""
    while True:
        try:
            chunk = os.read(master, 4096)
        except OSError:
            break
        if not chunk:
            break
        out += chunk
    proc.wait(timeout=60)
    os.close(master)
    text = out.decode(errors="replace")
    assert proc.returncode == 0, text
    assert "visvec batch:" in text and "/12 [" in text  # tqdm's bar: done/total
    assert "visvec: 12 frames, 12 ok (100.0 %)" in text  # and the summary stays

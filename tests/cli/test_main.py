"""The command line's contract (visvec.cli.main): exit codes, one-line errors, a closed
pipe, Ctrl-C, help."""

import re
from pathlib import Path

import cv2
import pytest
from click.testing import CliRunner

from visvec.cli.frames import run_frames
from visvec.cli.main import cli
from visvec.data import Frame
from visvec.rig import load_rig

from conftest import CONFIGS, SAMPLES, besides_the_zero_tilt_note, rows_of, run

RIG = str(CONFIGS / "triangle.toml")


def test_bad_rig_exit_2_before_any_frame(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(Path(RIG).read_text().replace("fy = 600.0", ""))
    out = tmp_path / "rows.csv"
    r = run("batch", SAMPLES, "--rig", bad, "--out", out)
    assert r.exit_code == 2
    assert "bad.toml" in r.output and "[camera] fy" in r.output and "missing" in r.output
    assert not out.exists()


@pytest.mark.parametrize("what", ["missing_folder", "empty_folder", "missing_video"])
def test_unopenable_sources_exit_3(tmp_path, what):
    path = {
        "missing_folder": tmp_path / "nope",
        "empty_folder": tmp_path,
        "missing_video": tmp_path / "rec.avi",
    }[what]
    r = run("batch", path, "--rig", RIG)
    assert r.exit_code == 3
    assert str(path) in r.output


@pytest.mark.slow  # 8 s: the default run stays under 5 minutes
def test_a_reader_that_closes_the_pipe_ends_the_run_quietly(tmp_path):
    """`visvec batch ... | head -2`: the run ends with status 0 and no error message, and
    a calibration whose report is cut short has still written its file."""
    import subprocess
    import sys

    rig320 = str(CONFIGS / "triangle-320.toml")
    frames = tmp_path / "level"
    r = run("simulate", "--rig", rig320, "--out", frames, "--frames", 40, "--motion", "level")
    assert r.exit_code == 0
    vis = [sys.executable, "-m", "visvec"]
    p = subprocess.Popen(
        [*vis, "batch", str(frames), "--rig", rig320],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert p.stdout.readline().startswith("frame,time_s,status")
    p.stdout.close()  # the reader is gone before the rows come
    assert p.wait(timeout=120) == 0
    assert besides_the_zero_tilt_note(p.stderr.read()) == ""
    cal = tmp_path / "cal.toml"
    cmd = [*vis, "calibrate", "zero-tilt", str(frames), "--rig", rig320, "--out", str(cal)]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    p.stdout.close()
    assert p.wait(timeout=120) == 0
    assert p.stderr.read() == ""
    assert "sigma_scale" in cal.read_text()


def test_ctrl_c_ends_cleanly_with_every_row_written(tmp_path):
    rig = load_rig(RIG)
    img = cv2.imread(str(sorted(SAMPLES.glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE)

    def frames():
        for i in range(3):
            yield Frame(i, i / 30, img, f"f{i}")
        raise KeyboardInterrupt

    out = tmp_path / "rows.csv"
    rows = run_frames(
        rig,
        frames(),
        out=str(out),
        fmt="csv",
        method="full",
        overlay=None,
        max_frames=None,
        keep_rows=True,
    )
    assert len(rows) == 3
    assert len(rows_of(out.read_text())) == 3


def test_unexpected_error_is_one_line_exit_1(monkeypatch):
    import visvec.cli.batch as b

    def boom(*a, **k):
        raise RuntimeError("kaboom")

    monkeypatch.setattr(b, "run_frames", boom)
    r = CliRunner().invoke(cli, ["batch", str(SAMPLES), "--rig", RIG])
    assert r.exit_code == 1
    assert "kaboom" in r.output and "Traceback" not in r.output


def test_misspelt_required_key_is_named(tmp_path):
    text = Path(RIG).read_text()
    assert "\nfx = " in text
    (tmp_path / "fxx.toml").write_text(text.replace("\nfx = ", "\nfxx = ", 1))
    r = run("batch", SAMPLES, "--rig", tmp_path / "fxx.toml")
    assert r.exit_code == 2 and "fx: missing (required); the file has 'fxx'" in r.stderr
    # a key of its own (fy) is not offered for a missing fx
    (tmp_path / "nofx.toml").write_text(
        "\n".join(x for x in text.splitlines() if not x.startswith("fx = "))
    )
    r = run("batch", SAMPLES, "--rig", tmp_path / "nofx.toml")
    assert r.exit_code == 2 and r.stderr.rstrip().endswith("fx: missing (required)")


def test_help_groups_the_options_of_each_kind():
    """`simulate --help`: the options for one target kind under that kind's heading,
    after the options for all; every option described; no range shown as None."""
    text = run("simulate", "--help").output
    heads = [line for line in text.splitlines() if line.endswith("options:") or line == "Options:"]
    assert heads == ["Input options:", "Rig options:", "Output options:", "Fusion options:",
                     "Triangle options:", "Markers options:", "Starfield options:",
                     "Lamps options:", "Options:"]  # fmt: skip
    tri = text.split("Triangle options:")[1].split("Markers options:")[0]
    assert "--blur" in tri and "--readout-ms" in tri and "--spurious" not in tri
    assert "--spurious" in text.split("Lamps options:")[1]
    assert "None]" not in text
    rate = run("rate", "--help").output
    assert "[required unless --budget]" in " ".join(rate.split())
    assert "--budget options:" in rate
    # track's options by what they are about
    track = run("track", "--help").output

    def under(head, text=track):
        return text.split(head)[1].split("options:")[0]

    assert "--rig" in under("Rig options:") and "--serve" in under("Live view options:")
    assert "--foxglove" in under("Live view options:") and "--imu" in under("Fusion options:")
    assert "--record" in under("Output options:") and "--camera " in under("Input options:")
    assert "--gyro-range-dps" in under("Fusion options:", run("fuse", "--help").output)


def test_version_says_which_path_the_triangle_runs(monkeypatch):
    """--version names the version and whether the compiled kernels (the fast extra)
    run, VISVEC_PURE turned them off, or how to install them."""
    from visvec import __version__, _kernels

    r = run("--version")
    assert r.exit_code == 0 and f"version {__version__}" in r.output
    if _kernels.AVAILABLE:
        assert "compiled (Numba " in r.output
    monkeypatch.setattr(_kernels, "AVAILABLE", False)
    monkeypatch.setattr(_kernels, "PURE", True)
    assert "in numpy (VISVEC_PURE is set)" in run("--version").output
    monkeypatch.setattr(_kernels, "PURE", False)
    assert 'pip install "visvec[fast]"' in run("--version").output


def test_each_command_lists_the_exit_codes_and_estimators_it_has():
    """A command's help ends with the exit codes it can give, not every command's; `rate`
    lists the starfield's estimators only."""

    def codes(*cmd):
        text = " ".join(run(*cmd, "--help").output.split())
        tail = text[text.index("Exit codes:") :]
        return {int(c) for c in re.findall(r"(?:^Exit codes: |; )(\d+) ", tail)}

    assert codes("track") == {0, 1, 2, 3, 4}
    assert codes("batch") == {0, 1, 2, 3, 4, 130}
    assert codes("simulate") == {0, 1, 2, 130}
    assert codes("plot") == codes("check") == {0, 1, 2}
    assert codes("calibrate", "zero-tilt") == {0, 1, 2, 3}
    assert codes() == {0, 1, 2, 3, 4, 130}  # the group's own help: every one
    rate = " ".join(run("rate", "--help").output.split())
    assert "[poisson|crassidis]" in rate and "pnp-" not in rate
    track = " ".join(run("track", "--help").output.split())
    assert "pnp-ippe" in track and "130" not in track

"""The fusion's input files: a bad line is refused by its number."""

import pytest
from fusion_cases import write

from visvec.errors import InputFileError
from visvec.fuse.inputs import read_fixes, read_imu
from visvec.output import PLANAR_COLUMNS


def test_bad_inertial_files_name_the_line(tmp_path):
    with pytest.raises(InputFileError, match="missing column.*ay_mps2"):
        read_imu(write(tmp_path, "a.csv", "time_s,gz_dps,ax_mps2\n0,0,0\n"), planar=True)
    with pytest.raises(InputFileError, match="line 3: gz_dps = 'x'"):
        read_imu(write(tmp_path, "b.csv", "time_s,gz_dps,ax_mps2,ay_mps2\n0,0,0,0\n0.01,x,0,0\n"),
                 planar=True)  # fmt: skip
    text = "time_s,gx_dps,gy_dps,gz_dps\n0,0,0,0\n0.01,0,0,0\n0.005,0,0,0\n"
    with pytest.raises(InputFileError, match="line 4: time_s = 0.005 does not increase.*line 3"):
        read_imu(write(tmp_path, "c.csv", text), planar=False)
    rows = "".join(f"{t:.2f},0,0,0\n" for t in [0, 0.01, 0.02, 0.03, 0.5, 0.51, 0.52])
    imu = read_imu(write(tmp_path, "d.csv", "time_s,gx_dps,gy_dps,gz_dps\n" + rows), planar=False)
    assert imu.gaps == (4,) and imu.lines[4] == 6


def test_bad_fixes_files_name_the_line(tmp_path):
    head = ",".join(PLANAR_COLUMNS) + "\n"
    good = "0,1.0,ok,1,2,3,0.1,0.1,0.01,0.1,9,600,\n"
    with pytest.raises(InputFileError, match="line 3: y_mm = 'abc'"):
        read_fixes(
            write(tmp_path, "a.csv", head + good + "1,2.0,ok,1,abc,3,0.1,0.1,0.01,0.1,9,600,\n")
        )
    with pytest.raises(InputFileError, match="line 2: status = 'fine'"):
        read_fixes(write(tmp_path, "b.csv", head + good.replace("ok", "fine")))
    with pytest.raises(InputFileError, match="planar pose columns"):
        read_fixes(write(tmp_path, "c.csv", "time_s,status,a\n1,ok,2\n"))
    with pytest.raises(InputFileError, match="line 2: quaternion norm"):
        read_fixes(write(tmp_path, "d.csv", "time_s,status,qw,qx,qy,qz\n1,ok,1,1,0,0\n"))
    # non-ok rows may have empty fields and are skipped
    fx = read_fixes(write(tmp_path, "e.csv", head + good + "1,2.0,rejected,,,,,,,,0,5,x\n"))
    assert len(fx.fixes) == 1 and fx.n_rows == 2 and fx.planar
    assert fx.fixes[0].available_s == pytest.approx(1.6)


def test_rows_read_late_are_no_fixes(tmp_path):
    """An ok row warned read_late (a live frame that waited before it was read: its time
    is later than its exposure by an unknown amount) is not a fix, from a file or live;
    its other warnings do not matter."""
    from visvec.fuse.live import parse_fix

    head = ",".join(PLANAR_COLUMNS) + "\n"
    rows = [
        "0,1.0,ok,1,2,3,0.1,0.1,0.01,0.1,9,6,\n",
        "1,1.1,ok,1,2,3,0.1,0.1,0.01,0.1,9,6,low_brightness;read_late\n",
        "2,1.2,ok,1,2,3,0.1,0.1,0.01,0.1,9,6,low_brightness\n",
    ]
    fx = read_fixes(write(tmp_path, "f.csv", head + "".join(rows)))
    assert [f.time_s for f in fx.fixes] == [1.0, 1.2] and fx.n_rows == 3
    keys = PLANAR_COLUMNS
    live = [dict(zip(keys, r.strip("\n").split(","), strict=False)) for r in rows]
    assert [parse_fix(r, planar=True) is None for r in live] == [False, True, False]

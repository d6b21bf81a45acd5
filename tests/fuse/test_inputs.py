"""The fusion's input files: a bad line is refused by its number."""

import numpy as np
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


def test_an_imu_file_s_header_declares_the_gyro_range(tmp_path):
    """'# gyro_range_dps = N' before the header: read as the gyro's range; lines are
    still numbered as in the file; a range that is not a positive finite number is
    refused naming its line."""
    good = "time_s,gx_dps,gy_dps,gz_dps\n0,0,0,0\n0.01,0,0,0\n"
    body = good + "0.02,x,0,0\n"
    with pytest.raises(InputFileError, match="line 6: gx_dps = 'x'"):
        read_imu(write(tmp_path, "a.csv", "# BMI088\n# gyro_range_dps = 2000\n" + body), False)
    imu = read_imu(write(tmp_path, "b.csv", "# gyro_range_dps: 2000\n" + good), False)
    assert imu.gyro_range_dps == 2000.0 and imu.lines.tolist() == [3, 4]
    assert read_imu(write(tmp_path, "c.csv", good), False).gyro_range_dps is None
    for bad in ("0", "-250", "nan", "inf", "fast"):
        with pytest.raises(InputFileError, match=f"line 2: gyro_range_dps = '{bad}'"):
            read_imu(write(tmp_path, "d.csv", f"# IMU\n# gyro_range_dps = {bad}\n" + body), False)


def _attitude_row(cov_euler_deg2):
    from visvec.data import AttitudeSolution, Status
    from visvec.output import attitude_row
    from visvec.rotations import euler_to_matrix

    R = euler_to_matrix(*np.radians([30.0, 10.0, -5.0]))
    row = attitude_row(3, 1.5, AttitudeSolution(Status.OK, R_nb=R, cov_b=np.eye(3)),
                       Status.OK, (), latency_ms=40.0)  # fmt: skip
    from dataclasses import replace

    sig = np.sqrt(np.diag(cov_euler_deg2))
    return replace(row, cov=np.asarray(cov_euler_deg2), sigma_deg=sig), R


COV_E = np.array([[0.04, -0.0116, 0.0], [-0.0116, 0.04, 0.001], [0.0, 0.001, 0.09]])  # deg^2


def test_a_fix_from_a_row_keeps_its_full_covariance(tmp_path):
    """The triangle's yaw-pitch correlation (-0.29 here) reaches the filter: in one
    process (fix_from_row), from a file with --covariance columns (read_fixes) and from a
    live text row (parse_fix), the same body-axis covariance; from sigmas alone it is
    lost (the correlation is what differs)."""
    import csv

    from visvec.fuse.inputs import _fix_cov, fix_cov, fix_from_row
    from visvec.fuse.live import parse_fix
    from visvec.output import AttitudeRow

    row, R = _attitude_row(COV_E)
    want = fix_cov(COV_E, R, planar=False)
    f = fix_from_row(row, planar=False)
    np.testing.assert_allclose(f.cov, want, rtol=1e-12)
    assert f.time_s == 1.5 and f.available_s == pytest.approx(1.54)
    diag = _fix_cov(np.sqrt(np.diag(COV_E)), R, planar=False)
    assert np.abs(diag - want).max() > 0.1 * np.abs(want).max()
    cols = (*AttitudeRow.columns, *AttitudeRow.cov_columns())
    d = {**row.as_dict(), **row.cov_dict()}
    text = {k: "" if d[k] is None else str(d[k]) for k in cols}
    p = tmp_path / "fixes.csv"
    with open(p, "w", newline="") as fh:
        wr = csv.DictWriter(fh, cols)
        wr.writeheader()
        wr.writerow(text)
    np.testing.assert_allclose(read_fixes(p).fixes[0].cov, want, rtol=1e-5)
    np.testing.assert_allclose(parse_fix(text, planar=False).cov, want, rtol=1e-5)
    # a covariance that is none is refused, naming the line
    text["cov_yaw_pitch"] = "0.5"
    with open(p, "w", newline="") as fh:
        wr = csv.DictWriter(fh, cols)
        wr.writeheader()
        wr.writerow(text)
    with pytest.raises(InputFileError, match="line 2: the cov_\\* columns are not a covariance"):
        read_fixes(p)

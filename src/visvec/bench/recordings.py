"""Real IMU recordings with motion-capture truth, as the fusion benchmark and tests read
them: RepoIMU's T-stick trials (Szczesna et al., ICCVG 2016; a 100 Hz gyro whose range,
about 422 deg/s, some trials exceed) and BROAD (Laidig, Caruso, Cereatti, Seel, Data
6(7), 2021; a 286 Hz gyro of 2000 deg/s range, optical truth). Both give the truth as
R_NB, the gyro in body axes (rad/s)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visvec.rotations import quat_to_matrix

REPOIMU_TRIALS = ("Test02_Trial1", "Test04_Trial1", "Test05_Trial2", "Test06_Trial2",
                  "Test10_Trial1", "Test11_Trial1")  # fmt: skip
# RepoIMU's trials whose gyro clips at its range (Test05 in over a thousand samples)
REPOIMU_CLIPPING = ("Test05_Trial2", "Test10_Trial1")
# ... and the one whose gyro clips once: Test06's y axis at -408 deg/s for 18 samples
# from 48.63 s (steps of 0.0-0.3 deg/s while x swings by 150 deg/s)
REPOIMU_CLIPS_ONCE = ("Test06_Trial2",)
BROAD_TRIALS = ("01_undisturbed_slow_rotation_A", "06_undisturbed_fast_rotation_A",
                "08_undisturbed_fast_rotation_with_breaks_A",
                "15_undisturbed_fast_translation_A",
                "18_undisturbed_fast_translation_with_breaks_B", "25_disturbed_tapping_B",
                "26_disturbed_phone_vibration_A")  # fmt: skip


@dataclass(frozen=True)
class Recording:
    """One trial: sample times ``t`` (n,) s, the gyro (n, 3) rad/s, the truth R_NB
    (n, 3, 3) and where it is known (``truth_ok`` (n,): the motion capture saw the
    markers), the dataset's name."""

    name: str
    dataset: str
    t: np.ndarray
    gyro: np.ndarray
    R: np.ndarray
    truth_ok: np.ndarray


def repoimu(path: str | Path) -> Recording:
    """A RepoIMU T-stick CSV (semicolon-separated, two header rows: time s, Vicon
    quaternion w x y z, accelerometer, gyro rad/s, magnetometer). The motion capture
    reports the identity before it tracks: such rows are not truth."""
    path = Path(path)
    rows = []
    with open(path) as fh:
        for i, line in enumerate(fh):
            if i >= 2:
                rows.append([float(x) for x in line.strip().rstrip(";").split(";")[:14]])
    a = np.array(rows)
    q = a[:, 1:5] / np.linalg.norm(a[:, 1:5], axis=1)[:, None]
    R = np.array([quat_to_matrix(x) for x in q])
    ok = ~np.all(np.abs(R - np.eye(3)) < 1e-9, axis=(1, 2))
    return Recording(path.stem.removeprefix("TStick_"), "RepoIMU", a[:, 0], a[:, 8:11], R, ok)


def broad(path: str | Path) -> Recording:
    """A BROAD trial's .mat file (imu_gyr rad/s, opt_quat w x y z, NaN where the
    markers were lost, sampling_rate); times from the sample index."""
    from scipy.io import loadmat

    path = Path(path)
    d = loadmat(path)
    fs = float(np.asarray(d["sampling_rate"]).ravel()[0])
    q = np.asarray(d["opt_quat"], float)
    ok = np.all(np.isfinite(q), axis=1)
    qn = np.where(ok[:, None], q, [1.0, 0.0, 0.0, 0.0])
    qn = qn / np.linalg.norm(qn, axis=1)[:, None]
    R = np.array([quat_to_matrix(x) for x in qn])
    gyro = np.asarray(d["imu_gyr"], float)
    return Recording(path.stem, "BROAD", np.arange(len(gyro)) / fs, gyro, R, ok)


def shared_recordings(data: str | Path) -> list[tuple[str, Path]]:
    """(dataset, path) of every shared trial under ``data`` (../shared/data) that is
    there, RepoIMU's first."""
    data = Path(data)
    out = [("RepoIMU", data / "repoimu" / f"TStick_{n}.csv") for n in REPOIMU_TRIALS]
    out += [("BROAD", data / "broad" / f"{n}.mat") for n in BROAD_TRIALS]
    return [(k, p) for k, p in out if p.exists()]


def load(dataset: str, path: str | Path) -> Recording:
    return repoimu(path) if dataset == "RepoIMU" else broad(path)

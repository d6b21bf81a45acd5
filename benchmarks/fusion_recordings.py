"""3-D fusion on real IMU recordings: every shared RepoIMU T-stick trial (Szczesna et al.
2016; a 100 Hz gyro with Vicon quaternions as the truth, clipping at its 422 deg/s range
in Test05 and Test10) and every shared BROAD trial (Laidig et al. 2021; a 286 Hz gyro of
2,000 deg/s range with optical truth, rotation up to 1,350 deg/s, tapping, vibration).

Fixes are the truth decimated to 2 Hz, delayed 0.6 s (latency_ms = 600) and with
0.1 deg of noise per body axis (none where the markers were lost), written as a camera's
rows with `--covariance` (that noise's Euler covariance); the gyro is the real
one, with its real bias, noise, misalignment to the truth's body frame, time offset and
(RepoIMU Test05, Test10) saturation. Everything goes through `visvec fuse` with its
default options (nothing tuned per trial or per dataset; the gyro's range not given) and
is compared against the truth at every IMU sample from the first fix on, beside
- re-anchor: the simplest rule, the latest fix available plus the gyro (less its mean
  over the first 2 s, trapezoidal steps) integrated from the fix's exposure to now;
- gyro alone: from the first fix's attitude, the same bias;
- fixes alone: the latest fix available;
- the hindsight floor (what the data allow beyond any causal filter, below).

Per trial also the samples flagged `gyro_saturated` (none may be, on a gyro that does not
clip) and the sigma's calibration (ok rows beyond 3 and 5 sigma), judged against the
truth smoothed by the calibrated gyro (smoothed_reference: the motion capture's own
noise is as large as a row's sigma at rest) and, for comparison, the raw truth. Test05_Trial2 is the
fault case: the gyro saturates in over a thousand samples and the motion capture jumps by
up to 150 deg between samples (so some fixes are wrong too); its figures are kept apart
and judged on the honesty of the rows, not their RMS.

    python benchmarks/fusion_recordings.py [--seed 0] [--trials Test02_Trial1,06_...]
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from visvec.bench.recordings import load, shared_recordings
from visvec.output import AttitudeRow
from visvec.rotations import (
    euler_rates_from_body,
    expmap,
    logmap,
    matrix_to_euler,
    matrix_to_quat,
    quat_to_matrix,
)

from _common import OUT, ROOT, pyplot, run_record, save_json

DATA = ROOT.parent / "shared" / "data"
FAULT_TRIAL = "Test05_Trial2"
# the samples the benchmark counts as clipped (the truth's knowledge, not visvec's):
# RepoIMU's T-stick beyond 98 % of its smaller side's level
CLIP_DPS = {"RepoIMU": 0.98 * 415.9, "BROAD": None}
FIX_HZ, DELAY_S, NOISE_DEG, REST_S = 2.0, 0.6, 0.1, 2.0
STRETCH_DEG, STRETCH_S = 3.0, 1.5
PITCH_MAX_DEG = 85.0
# the reference and the calibrated gyro agree within this over 0.1 s (benchmark's agrees)
AGREE_DPS, AGREE_SHARE = 5.0, 0.10
# and the reference's path within this of the calibrated gyro's over 0.1 s (steady)
SPIKE_DEG, SPIKE_SPAN = 0.15, 1.0
# the motion capture's rate over 0.1 s at rest: at most 0.92 deg/s over the rest windows
# (gyro under 1 deg/s) of every trial but the fault case
REF_REST_DPS = 1.0
# the sigma is judged against the truth smoothed by the calibrated gyro: each sample's
# reference the median of the truth over SMOOTH_S either side, every truth sample
# carried to it by the gyro; a sample whose window holds valid truth for under half its
# span, or under SMOOTH_SUPPORT of them within SMOOTH_AGREE_DEG of that median (a jump of
# the motion capture lasting a third of the window), has no reference
SMOOTH_S, SMOOTH_SUPPORT, SMOOTH_AGREE_DEG = 0.5, 2.0 / 3.0, 1.0


def angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(logmap(Ra.T @ Rb))))


def stats(e: np.ndarray, t: np.ndarray, valid: np.ndarray) -> dict:
    """Error figures over the samples with a valid reference; a stretch over
    STRETCH_DEG is of consecutive samples, so a sample without a valid reference (its
    error unknown) ends one: the stretches on either side of it are not joined."""
    ev = e[valid]
    return {
        "rms_deg": float(np.sqrt(np.mean(ev**2))),
        "median_deg": float(np.median(ev)),
        "p95_deg": float(np.percentile(ev, 95)),
        "max_deg": float(ev.max()),
        "longest_over_3deg_s": longest((e > STRETCH_DEG) & valid, t),
    }


def longest(mask: np.ndarray, t: np.ndarray) -> float:
    """The longest time span of consecutive True samples."""
    best, start = 0.0, None
    for i, m in enumerate(mask):
        if m and start is None:
            start = i
        if start is not None and (not m or i == len(mask) - 1):
            end = i if m else i - 1
            best = max(best, float(t[end] - t[start]) + float(np.median(np.diff(t))))
            start = None
    return best


def reference_valid(rec, clipped: np.ndarray) -> np.ndarray:
    """Samples where the motion capture can serve as truth: where it saw the markers,
    not a stretch (0.1 s windows) where it stands still (turns no faster than at rest,
    REF_REST_DPS) while the gyro turns at over 5 deg/s (RepoIMU Test10 from 3.3 to 3.9
    s: 0.04-0.55 deg/s against the gyro's 10-28), and not one where its own rate
    departs from a gyro within its range by over 20 deg/s + 10 % (a reference glitch
    that no gyro calibration explains: Test10 from 3.9 to 4.9 s, Test05's jumps)."""
    t, R, gyro = rec.t, rec.R, rec.gyro
    n = len(t)
    ok = rec.truth_ok.copy()
    W = max(2, int(round(0.1 / np.median(np.diff(t)))))
    for i in range(0, n - W, W // 2):
        if not (rec.truth_ok[i] and rec.truth_ok[i + W]) or clipped[i : i + W + 1].any():
            continue
        w_ref = logmap(R[i].T @ R[i + W]) / (t[i + W] - t[i])
        w_g = gyro[i : i + W + 1].mean(axis=0)
        if np.linalg.norm(w_ref - w_g) > np.radians(20) + 0.1 * np.linalg.norm(w_g):
            ok[i : i + W + 1] = False
        # a reference that does not move while the gyro turns is not tracking
        if np.linalg.norm(w_ref) < np.radians(REF_REST_DPS) and np.linalg.norm(w_g) > np.radians(5):
            ok[i : i + W + 1] = False
    return ok


def write_inputs(tmp: Path, t, gyro, R_true, rng, truth_ok):
    """The IMU and fixes CSVs as visvec reads them (a fix where the truth is known);
    the fixes' indices and attitudes."""
    with open(tmp / "imu.csv", "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(["time_s", "gx_dps", "gy_dps", "gz_dps"])
        for ti, g in zip(t, np.degrees(gyro), strict=True):
            wr.writerow([f"{ti:.4f}", *(f"{x:.6f}" for x in g)])
    step = int(round(1.0 / (FIX_HZ * np.median(np.diff(t)))))
    idx = np.arange(0, len(t), step)
    idx = idx[truth_ok[idx]]
    fixes_R = []
    with open(tmp / "fixes.csv", "w", newline="") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(["frame", "time_s", "status", "yaw_deg", "pitch_deg", "roll_deg", "qw",
                     "qx", "qy", "qz", "sigma_yaw_deg", "sigma_pitch_deg", "sigma_roll_deg",
                     *AttitudeRow.cov_columns(), "rms_px", "n_points", "latency_ms",
                     "warnings"])  # fmt: skip
        for k, i in enumerate(idx):
            Rf = R_true[i] @ expmap(np.radians(NOISE_DEG) * rng.standard_normal(3))
            fixes_R.append(Rf)
            e = matrix_to_euler(Rf)
            # the Euler covariance of an isotropic 0.1 deg body-axis noise (J NOISE^2 J^T,
            # deg^2), as a camera's row with --covariance gives it: its yaw and roll
            # grow as 1 / cos(pitch) and correlate; `fuse` takes it back to the body axes
            J = euler_rates_from_body(*e)
            C = NOISE_DEG**2 * J @ J.T
            wr.writerow([k, f"{t[i]:.4f}", "ok", *(f"{x:.6f}" for x in np.degrees(e)),
                         *(f"{x:.9f}" for x in matrix_to_quat(Rf)),
                         *(f"{x:.6f}" for x in np.sqrt(np.diag(C))),
                         *(f"{C[a, b]:.9g}" for a in range(3) for b in range(a, 3)), "", "",
                         DELAY_S * 1000, ""])  # fmt: skip
    return idx, fixes_R


def run_fuse(tmp: Path) -> tuple[list[dict], str, float]:
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "visvec", "fuse", "--imu", str(tmp / "imu.csv"),
           "--fixes", str(tmp / "fixes.csv"), "--out", str(tmp / "fused.csv")]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        sys.exit(res.stderr)
    with open(tmp / "fused.csv") as fh:
        return list(csv.DictReader(fh)), res.stderr, time.perf_counter() - t0


def reanchor(t, D, anchors, idx, R_true, first) -> np.ndarray:
    """Errors (deg), from sample `first` on, of the re-anchor rule: the latest fix
    available (attitude anchors[j], exposed at sample idx[j], available DELAY_S later)
    carried forward by each sample's rotation D (see _steps) from its exposure to now."""
    avail = t[idx] + DELAY_S
    e, j_cur, Rc = [], -1, None
    for i in range(len(t)):
        j = int(np.searchsorted(avail, t[i], side="right")) - 1
        if j >= 0 and j != j_cur:
            # a new fix: start again from its exposure and integrate up to now
            j_cur, Rc = j, anchors[j].copy()
            for m in range(idx[j] + 1, i + 1):
                Rc = Rc @ D[m]
        elif Rc is not None:
            Rc = Rc @ D[i]
        if i >= first:
            e.append(angle_deg(R_true[i], Rc))
    return np.array(e)


def baselines(t, gyro, R_true, idx, fixes_R, first):
    """Errors from `first` on of re-anchor, gyro alone and fixes alone."""
    bias = gyro[t < t[0] + REST_S].mean(axis=0)
    D = _steps(gyro - bias, t)
    avail = t[idx] + DELAY_S
    e_gy, e_fx = [], []
    R_g = fixes_R[0].copy()
    for i in range(len(t)):
        if i > 0:
            R_g = R_g @ D[i]
        if i >= first:
            j = int(np.searchsorted(avail, t[i], side="right")) - 1
            e_gy.append(angle_deg(R_true[i], R_g))
            e_fx.append(angle_deg(R_true[i], fixes_R[j]))
    return reanchor(t, D, fixes_R, idx, R_true, first), np.array(e_gy), np.array(e_fx)


def _steps(w: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Each sample's rotation over the interval before it (trapezoidal body rate w)."""
    from scipy.spatial.transform import Rotation

    rv = np.zeros_like(w)
    rv[1:] = 0.5 * (w[1:] + w[:-1]) * np.diff(t)[:, None]
    return Rotation.from_rotvec(rv).as_matrix()


def agrees(t, R, w, clip) -> np.ndarray:
    """Samples where the reference agrees with the gyro calibrated in hindsight (``w``:
    bias, misalignment, scale factors and time offset fitted): over every 0.1 s window,
    their rates within AGREE_DPS + AGREE_SHARE of the rate (unclipped windows). Where
    they part by more, no calibration explains it: the reference turns when the gyro
    does not (RepoIMU Test06 at 3.5-3.9 s: 0.2 s behind the gyro at a start; Test02 at
    17.7 s: 11 deg/s faster than the gyro reads), or the gyro turns when the reference
    does not; which one is wrong the data cannot tell, and the rows there are not
    judged."""
    n = len(t)
    ok = np.ones(n, bool)
    W = max(2, int(round(0.1 / np.median(np.diff(t)))))
    for i in range(0, n - W, W // 2):
        if clip[i : i + W + 1].any():
            continue
        w_ref = logmap(R[i].T @ R[i + W]) / (t[i + W] - t[i])
        w_g = w[i : i + W + 1].mean(axis=0)
        if np.linalg.norm(w_ref - w_g) > np.radians(AGREE_DPS) + AGREE_SHARE * np.linalg.norm(w_g):
            ok[i : i + W + 1] = False
    return ok


def steady(t, R, w, truth_ok) -> np.ndarray:
    """Samples where the reference does not jump off its path and back: at a sample i,
    the calibrated gyro (``w``) carries the reference from 0.1 s before and back from
    0.1 s after; if both miss R[i] by more than SPIKE_DEG plus SPIKE_SPAN times what the
    gyro misses over the whole 0.2 s (R[i - W] carried to R[i + W]: the calibration's
    own residual there), the reference jumped at i and came back (BROAD 01 at 32.43 s:
    0.5 deg for 20 ms while the gyro is still), a glitch of the motion capture, and the
    rows there are not judged. A calibration residual that grows through the window
    misses R[i] from one side or the other by at most about half the span: it is never
    taken for a jump."""
    from scipy.spatial.transform import Rotation

    def miss(A, B):  # the angle (deg) between rotations, batched
        return np.degrees(np.linalg.norm(
            Rotation.from_matrix(np.einsum("nji,njk->nik", A, B)).as_rotvec(), axis=1))  # fmt: skip

    n = len(t)
    W = max(2, int(round(0.1 / np.median(np.diff(t)))))
    D = _steps(w, t)
    G = np.repeat(np.eye(3)[None], n - W, axis=0)
    for h in range(1, W + 1):
        G = G @ D[h : n - W + h]  # G[i]: the gyro's turn from sample i to i + W
    m = n - 2 * W
    i = np.arange(W, n - W)
    from_before = miss(np.einsum("nij,njk->nik", R[i - W], G[i - W]), R[i])
    from_after = miss(np.einsum("nij,nkj->nik", R[i + W], G[i]), R[i])
    span = miss(np.einsum("nij,njk,nkl->nil", R[i - W], G[i - W], G[i]), R[i + W])
    jump = np.minimum(from_before, from_after) > SPIKE_DEG + SPIKE_SPAN * span
    ok = np.ones(n, bool)
    ok[W : W + m] = ~(jump & truth_ok[i - W] & truth_ok[i + W])
    return ok


def smoothed_reference(t, R, w, valid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The truth with its own noise averaged out, for judging the rows' sigma: the
    motion capture jitters by 0.04-0.15 deg (median per trial) with spikes of
    0.3-0.7 deg while the gyro is still (BROAD 18 at 104-105 s), as much as the rows'
    own sigma at rest, so against the raw truth a row's z measures the truth's noise.
    The calibrated gyro ``w`` (hindsight) carries each valid truth sample R[j] to
    sample i (R[j] Q[j]^T Q[i], Q the gyro's attitude from the start, whose drift over
    0.5 s is far below the truth's noise); the reference at i is their median over
    SMOOTH_S either side (by 0.1 s blocks). Returns the reference (n, 3, 3), where it
    holds (SMOOTH_SUPPORT of its window's valid samples agree within SMOOTH_AGREE_DEG),
    and each sample's truth minus reference (deg, the truth's own noise)."""
    from scipy.spatial.transform import Rotation

    n = len(t)
    D = _steps(w, t)
    Q = np.empty_like(D)
    Q[0] = np.eye(3)
    for i in range(1, n):
        Q[i] = Q[i - 1] @ D[i]
    A = np.einsum("nij,nkj->nik", R, Q)  # R_j Q_j^T: constant for a perfect gyro and truth
    dt = float(np.median(np.diff(t)))
    H, B = int(round(SMOOTH_S / dt)), max(1, int(round(0.1 / dt)))
    Abar = np.full_like(A, np.nan)
    held = np.zeros(n, bool)
    for c in range(0, n, B):
        lo, hi = max(0, c - H), min(n, c + B + H)
        m = np.nonzero(valid[lo:hi])[0] + lo
        if len(m) < H:
            continue
        v = Rotation.from_matrix(np.einsum("ji,njk->nik", A[c], A[m])).as_rotvec()
        med = np.median(v, axis=0)
        agree = np.degrees(np.linalg.norm(v - med, axis=1)) <= SMOOTH_AGREE_DEG
        Abar[c : c + B] = A[c] @ expmap(med)
        held[c : c + B] = agree.sum() >= SMOOTH_SUPPORT * len(m)
    Rs = np.einsum("nij,njk->nik", np.where(held[:, None, None], Abar, np.eye(3)), Q)
    noise = np.degrees(np.linalg.norm(
        Rotation.from_matrix(np.einsum("nji,njk->nik", R, Rs)).as_rotvec(), axis=1))  # fmt: skip
    return Rs, held, noise


def hindsight_floor(t, R_true, gyro, valid, idx, first, clip) -> dict:
    """What the data allow, beyond any causal filter: the re-anchor rule with perfect
    fixes (2 Hz, 0.6 s late) and the gyro calibrated in hindsight: bias, misalignment,
    scale factors and time offset fitted by least squares over the whole trial to the
    reference's attitude change over 0.5 s windows (valid, unclipped). "as read" keeps
    the clipped samples as they are; "reference in clipped" puts the reference's own
    rate (central differences, through the fitted calibration) into the samples within
    2 % of the range (``clip``), which the gyro did not measure. The window residual is
    the gyro's disagreement with the reference that the calibration cannot explain;
    "_valid": ``valid`` where the reference also agrees with the calibrated gyro
    (agrees)."""
    from scipy.optimize import least_squares

    H = int(round(0.5 / np.median(np.diff(t))))
    n = len(t)
    gdot = np.gradient(gyro, t, axis=0)

    def rates(p, g):
        return (g + p[3] * gdot - p[0:3]) @ (expmap(p[4:7]) * (1 + p[7:10])).T

    ok = np.array([valid[i : i + H + 1].all() and not clip[i : i + H + 1].any()
                   for i in range(n - H)])  # fmt: skip
    starts = np.nonzero(ok)[0][::7]
    starts = starts[:: max(1, len(starts) // 400)]

    def residual(p):
        D = _steps(rates(p, gyro), t)
        Rw = R_true[starts]
        for h in range(1, H + 1):
            Rw = Rw @ D[starts + h]
        E = np.einsum("nji,njk->nik", R_true[starts + H], Rw)
        return np.array([logmap(x) for x in E]).ravel()

    p0 = np.zeros(10)
    p0[0:3] = gyro[t < t[0] + REST_S].mean(axis=0)
    p = least_squares(residual, p0).x
    w = rates(p, gyro)
    w_ref = np.zeros_like(w)
    for i in range(1, n - 1):
        w_ref[i] = logmap(R_true[i - 1].T @ R_true[i + 1]) / (t[i + 1] - t[i - 1])
    valid = valid & agrees(t, R_true, w, clip) & steady(t, R_true, w, valid)
    out = {"window_residual_deg": float(np.degrees(np.sqrt(np.mean(residual(p) ** 2) * 3))),
           "time_offset_ms": 1000 * float(p[3]), "_valid": valid, "_w": w}  # fmt: skip
    for key, ww in (("as_read", w), ("reference_in_clipped", np.where(clip[:, None], w_ref, w))):
        e = reanchor(t, _steps(ww, t), R_true[idx], idx, R_true, first)
        out[key + "_rms_deg"] = float(np.sqrt(np.mean(e[valid[first:]] ** 2)))
    return out


def trial(dataset: str, path: Path, rng) -> dict:
    rec = load(dataset, path)
    t, gyro, R_true = rec.t, rec.gyro, rec.R
    clip_dps = CLIP_DPS[dataset]
    clip = (np.degrees(np.abs(gyro)).max(axis=1) > clip_dps if clip_dps is not None
            else np.zeros(len(t), bool))  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        idx, fixes_R = write_inputs(tmp, t, gyro, R_true, rng, rec.truth_ok)
        rows, stderr, wall = run_fuse(tmp)
    # the first sample at or after the first fix is available
    first = int(np.searchsorted(t, t[idx[0]] + DELAY_S, side="left"))
    e_re, e_gy, e_fx = baselines(t, gyro, R_true, idx, fixes_R, first)
    floor = hindsight_floor(t, R_true, gyro, reference_valid(rec, clip), idx, first, clip)
    valid_all = floor.pop("_valid")
    R_ref, held, ref_noise = smoothed_reference(t, R_true, floor.pop("_w"), valid_all)
    valid = valid_all[first:]
    ts = t[first:]
    e, z, z_raw, ok, warn, sat, pitch = [], [], [], [], [], [], []
    for r in rows[first:]:
        qf = np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")]) if r["qw"] else None
        i = int(r["frame"])
        ok.append(r["status"] == "ok")
        warn.append(bool(r["warnings"]))
        sat.append("gyro_saturated" in r["warnings"])
        if qf is None:
            e.append(np.nan)
            z.append(np.full(3, np.nan))
            z_raw.append(np.full(3, np.nan))
            pitch.append(0.0)
            continue
        e.append(angle_deg(R_true[i], quat_to_matrix(qf)))
        # the row's promise: each Euler angle within its own sigma, against the
        # smoothed reference (and, for comparison, the raw truth)
        sig = np.array([float(r[f"sigma_{k}_deg"]) for k in ("yaw", "pitch", "roll")])
        ef = np.array(matrix_to_euler(quat_to_matrix(qf)))
        for out, Rt in ((z, R_ref[i]), (z_raw, R_true[i])):
            d = (np.degrees(ef - np.array(matrix_to_euler(Rt))) + 180.0) % 360.0 - 180.0
            out.append(np.abs(d) / sig)
        pitch.append(abs(np.degrees(matrix_to_euler(R_ref[i])[1])))
    e, z, ok, warn = np.array(e), np.array(z), np.array(ok), np.array(warn)
    z_raw = np.array(z_raw)
    sat, pitch = np.array(sat), np.array(pitch)
    zmax = np.nanmax(z, axis=1)
    fused = stats(np.where(np.isnan(e), 180.0, e), ts, valid)
    # the sigma's calibration on the ok rows, away from the Euler angles' singularity
    # (pitch within PITCH_MAX_DEG of 90 deg: yaw and roll are not defined there, and
    # their linearised sigmas do not hold)
    sel_raw = ok & valid & (pitch < PITCH_MAX_DEG)
    sel = sel_raw & held[first:]
    clean = sel & ~warn
    fused.update(
        {
            "reference_valid_share": float(valid.mean()),
            "ok_share": float(ok.mean()),
            "calibration_share": float(sel.mean()),
            "ok_axes_beyond_3sigma": float(np.mean(z[sel] > 3.0)),
            "ok_axes_beyond_5sigma": int(np.sum(z[sel] > 5.0)),
            "raw_truth_ok_axes_beyond_3sigma": float(np.mean(z_raw[sel_raw] > 3.0)),
            "raw_truth_ok_axes_beyond_5sigma": int(np.sum(z_raw[sel_raw] > 5.0)),
            "truth_noise_median_deg": float(np.median(ref_noise[valid_all & held])),
            "truth_noise_p95_deg": float(np.percentile(ref_noise[valid_all & held], 95)),
            "smoothed_reference_share": float(np.mean(held[first:] & valid)),
            "unwarned_ok_axes_beyond_5sigma": int(np.sum(z[clean] > 5.0)),
            "longest_ok_beyond_3sigma_s": longest(sel & (zmax > 3.0), ts),
            "longest_unwarned_ok_beyond_3sigma_s": longest(clean & (zmax > 3.0), ts),
            "saturated_rows": int(sat.sum()),
            "wall_s": wall,
            "samples_per_s": len(t) / wall,
            "stderr": stderr.strip().splitlines(),
        }
    )
    return {
        "dataset": dataset,
        "samples": len(t),
        "rate_hz": float(1.0 / np.median(np.diff(t))),
        "fixes": len(idx),
        "max_gyro_dps": float(np.degrees(np.abs(gyro)).max()),
        "clipped_samples": int(clip.sum()),
        "fused": fused,
        "reanchor": stats(e_re, ts, valid),
        "gyro_alone": stats(e_gy, ts, valid),
        "fixes_alone": stats(e_fx, ts, valid),
        "hindsight_floor": floor,
        # plotted where the truth is judged (elsewhere it may be the identity the
        # motion capture reports while it has lost the markers)
        "_plot": (ts, np.where(valid, e, np.nan), np.where(valid, e_re, np.nan)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--trials", default=None, help="names, comma-separated (default: all)")
    args = ap.parse_args()
    every = shared_recordings(DATA)
    if not every:
        sys.exit(f"no shared recordings under {DATA}")
    names = [p.stem.removeprefix("TStick_") for _, p in every]
    chosen = args.trials.split(",") if args.trials else names
    res = {}
    for k, (dataset, path) in enumerate(every):
        name = names[k]
        if name not in chosen:
            continue
        rng = np.random.default_rng([args.seed, k])
        res[name] = trial(dataset, path, rng)
        f, r = res[name]["fused"], res[name]["reanchor"]
        h = res[name]["hindsight_floor"]
        print(
            f"{name}: fused {f['rms_deg']:.3f} deg RMS (p95 {f['p95_deg']:.2f}; ok axes >3 "
            f"sigma {100 * f['ok_axes_beyond_3sigma']:.2f} %, >5: {f['ok_axes_beyond_5sigma']} "
            f"(raw truth {100 * f['raw_truth_ok_axes_beyond_3sigma']:.2f} %, "
            f"{f['raw_truth_ok_axes_beyond_5sigma']}; its noise median "
            f"{f['truth_noise_median_deg']:.3f} deg), "
            f"unwarned >5: {f['unwarned_ok_axes_beyond_5sigma']}; saturated rows "
            f"{f['saturated_rows']}; {f['samples_per_s']:.0f} samples/s); re-anchor "
            f"{r['rms_deg']:.3f}; gyro {res[name]['gyro_alone']['rms_deg']:.2f}; fixes "
            f"{res[name]['fixes_alone']['rms_deg']:.2f}; hindsight floor "
            f"{h['as_read_rms_deg']:.3f} as read, {h['reference_in_clipped_rms_deg']:.3f} "
            "with the reference in clipped samples",
            flush=True,
        )
    plots = {k: v.pop("_plot") for k, v in res.items()}
    out = {**run_record(), "fix_rate_hz": FIX_HZ, "delay_s": DELAY_S,
           "fix_noise_deg": NOISE_DEG, "trials": res}  # fmt: skip
    save_json("fusion_recordings", out)
    try:
        plt = pyplot()
    except ImportError:
        return
    fig, axes = plt.subplots(len(plots), 1, figsize=(10, 1.8 * len(plots)))
    for ax, (name, (ts, e, e_re)) in zip(np.atleast_1d(axes), plots.items(), strict=True):
        ax.semilogy(ts, np.maximum(e_re, 1e-3), lw=0.6, label="re-anchor (latest fix + gyro)")
        ax.semilogy(ts, np.maximum(e, 1e-3), lw=0.7, label="visvec fuse (defaults)")
        ax.set_ylabel(f"{name[:18]}\nerror (deg)", fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    np.atleast_1d(axes)[0].legend(fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel("time (s)")
    fig.suptitle("RepoIMU and BROAD: fixes 2 Hz, 0.6 s late, 0.1 deg noise")
    fig.tight_layout()
    OUT.mkdir(exist_ok=True)
    fig.savefig(OUT / "fusion_recordings.png", dpi=90)
    print(json.dumps({k: {"fused": v["fused"]["rms_deg"], "reanchor": v["reanchor"]["rms_deg"]}
                      for k, v in res.items()}))  # fmt: skip


if __name__ == "__main__":
    main()

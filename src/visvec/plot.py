"""A run's figure for a lab report (`visvec plot`): its values against time with their
1-sigma bands and a strip of the rows' statuses; with a truth, the errors against time
with their 1- and 3-sigma bands and the histogram of error over sigma against the
Gaussian it should follow. For every kind of row visvec writes (attitude, rate, planar
pose, fused rows). matplotlib (the ``plot`` extra) draws it."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from visvec.errors import InputFileError
from visvec.evaluate import WRAPPED, read_truth, wrap_deg

# the kinds of rows, by their value columns
KINDS = {
    "attitude": ("yaw_deg", "pitch_deg", "roll_deg"),
    "rate": ("wx_dps", "wy_dps", "wz_dps"),
    "planar pose": ("x_mm", "y_mm", "heading_deg"),
}
STATUS_COLOURS = {
    "ok": "#2e9a4a",
    "rejected": "#e08a1e",
    "no_target": "#9aa0a6",
    "not_converged": "#8e44ad",
    "read_error": "#c62828",
}
UNITS = {"deg": "deg", "dps": "deg/s", "mm": "mm"}


def read_rows(path: str | Path) -> tuple[str, tuple[str, ...], dict[str, np.ndarray], list[str]]:
    """(kind, value columns, columns as arrays, statuses) of a visvec rows file (CSV or
    JSON lines); InputFileError naming the file and the columns it needs otherwise."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: not a UTF-8 text file of visvec rows") from None
    records: list[dict]
    first = text.lstrip()[:1]
    try:
        if first == "{":
            records = [json.loads(line) for line in text.splitlines() if line.strip()]
        else:
            records = list(csv.DictReader(text.splitlines()))
    except (ValueError, csv.Error) as exc:
        raise InputFileError(f"{path}: not visvec rows (CSV or JSON lines): {exc}") from None
    cols = set(records[0]) if records else set()
    kind = next((k for k, n in KINDS.items() if {"frame", "time_s", "status", *n,
                 *(f"sigma_{x}" for x in n)} <= cols), None)  # fmt: skip
    if kind is not None:
        names = KINDS[kind]
    else:
        wanted = " or ".join(
            "frame,time_s,status," + ",".join(n) + "," + ",".join(f"sigma_{x}" for x in n)
            for n in KINDS.values()
        )
        raise InputFileError(
            f"{path}: not visvec rows: needs the columns {wanted}; found "
            f"{sorted(cols) if cols else 'no rows'}"
        )

    def num(v) -> float:
        try:
            return float(v) if v not in ("", None) else math.nan
        except (TypeError, ValueError):
            return math.nan

    data = {k: np.array([num(r.get(k)) for r in records]) for k in
            ("frame", "time_s", *names, *(f"sigma_{n}" for n in names))}  # fmt: skip
    statuses = [str(r.get("status", "")) for r in records]
    return kind, names, data, statuses


def _unwrap_deg(a: np.ndarray) -> np.ndarray:
    out = a.copy()
    ok = np.isfinite(a)
    if ok.sum() > 1:
        out[ok] = np.degrees(np.unwrap(np.radians(a[ok])))
    return out


def _label(name: str) -> str:
    base, unit = name.rsplit("_", 1)
    return f"{base} ({UNITS.get(unit, unit)})"


def plot_run(rows_path: str | Path, out: str | Path, truth_path: str | Path | None = None,
             title: str | None = None) -> dict[str, object]:  # fmt: skip
    """Draw the figure of a rows file (and its truth) to ``out`` (.png, .svg or .pdf);
    returns what it drew (rows, ok rows, and with a truth the RMS errors and the share
    beyond 3 sigma). Left: each value with its 1-sigma band (and the truth), the
    statuses along time below; with a truth, right: each error in its 1- and 3-sigma
    bands, and below the error/sigma histogram against N(0, 1) with the figures."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kind, names, d, statuses = read_rows(rows_path)
    truth = read_truth(truth_path, names) if truth_path else None
    ok = np.array([s == "ok" for s in statuses])
    ncol = 2 if truth is not None else 1
    fig = plt.figure(figsize=(13 if ncol == 2 else 9, 10), constrained_layout=True)
    hr = [1, 1, 1, 0.18] + ([1.3] if truth is not None else [])
    gs = fig.add_gridspec(len(hr), ncol, height_ratios=hr)
    drew: dict[str, object] = {"kind": kind, "rows": len(d["time_s"]), "ok": int(ok.sum())}
    axes = _value_panels(fig, gs, names, d, ok, truth)
    _status_strip(fig.add_subplot(gs[3, :], sharex=axes[0]), d["time_s"], statuses, ok)
    if truth is not None:
        rms, z = _error_panels(fig, gs, names, d, ok, truth, axes[0])
        drew.update(_honesty_panels(fig, gs, names, rms, z, ok))
    fig.suptitle(title or f"{Path(rows_path).name}: {kind}")
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return drew


def _truth_of(truth: dict, d: dict, i: int) -> np.ndarray:
    """The truth's i-th value at each row's frame (NaN where the truth has no row)."""
    return np.array([truth[int(f)][i] if int(f) in truth else np.nan for f in d["frame"]])


def _value_panels(fig, gs, names, d, ok, truth) -> list:
    """Each value of the ok rows with its 1-sigma band, and the truth dashed."""
    t, axes = d["time_s"], []
    for i, n in enumerate(names):
        ax = fig.add_subplot(gs[i, 0], sharex=axes[0] if axes else None)
        axes.append(ax)
        v = np.where(ok, d[n], np.nan)
        s = np.where(ok, d[f"sigma_{n}"], np.nan)
        if n in WRAPPED:
            v = _unwrap_deg(v)
        ax.fill_between(t, v - s, v + s, color="#1f5fbf", alpha=0.25, lw=0, label="1 sigma")
        ax.plot(t, v, color="#1f5fbf", lw=1.0, label="rows")
        if truth is not None:
            tv = _truth_of(truth, d, i)
            if n in WRAPPED:  # the truth drawn on the rows' turn
                tv = v - wrap_deg(v - tv) if np.isfinite(v).any() else tv
            ax.plot(t, tv, color="k", lw=0.8, ls="--", label="truth")
        ax.set_ylabel(_label(n))
        ax.grid(alpha=0.3)
        if i == 0:
            ax.legend(loc="upper right", fontsize=8)
            ax.set_title("values (blue), 1-sigma band" + (", truth (dashed)" if truth else ""))
    return axes


def _status_strip(ax, t, statuses, ok) -> None:
    """The rows' statuses along time, one colour each."""
    from matplotlib.patches import Patch

    colours = [STATUS_COLOURS.get(s, "#444444") for s in statuses]
    step = np.diff(t[np.isfinite(t)])
    width = float(np.median(step)) if len(step) and np.median(step) > 0 else 1.0
    ax.bar(t, 1.0, width=width, color=colours, align="center", linewidth=0)
    ax.set_yticks([])
    ax.set_ylim(0, 1)
    ax.set_xlabel("time (s)")
    present = [s for s in STATUS_COLOURS if s in statuses]
    ax.legend(handles=[Patch(color=STATUS_COLOURS[s], label=s) for s in present],
              loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=7,
              frameon=False)  # fmt: skip
    ax.set_title(f"status: {int(ok.sum())} of {len(t)} rows ok", fontsize=9)


def _error_panels(fig, gs, names, d, ok, truth, ax0):
    """Each error against the truth in its 1- and 3-sigma bands: the RMS errors (per
    name) and every error/sigma."""
    t, zs, rms = d["time_s"], [], {}
    for i, n in enumerate(names):
        ax = fig.add_subplot(gs[i, 1], sharex=ax0)
        e = np.where(ok, d[n] - _truth_of(truth, d, i), np.nan)
        if n in WRAPPED:
            e = wrap_deg(e)
        s = np.where(ok, d[f"sigma_{n}"], np.nan)
        ax.fill_between(t, -3 * s, 3 * s, color="#1f5fbf", alpha=0.10, lw=0, label="3 sigma")
        ax.fill_between(t, -s, s, color="#1f5fbf", alpha=0.25, lw=0, label="1 sigma")
        ax.plot(t, e, color="#c0392b", lw=0.9, label="error")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("error " + _label(n))
        ax.grid(alpha=0.3)
        good = np.isfinite(e)
        rms[n] = float(np.sqrt(np.mean(e[good] ** 2))) if good.any() else None
        if i == 0:
            ax.legend(loc="upper right", fontsize=8)
            ax.set_title("errors against the truth")
        z = e[good] / s[good]
        zs.append(z[np.isfinite(z)])
    return rms, (np.concatenate(zs) if zs else np.zeros(0))


def _honesty_panels(fig, gs, names, rms, z, ok) -> dict[str, object]:
    """The error/sigma histogram against N(0, 1), and the figures beside it."""
    ax = fig.add_subplot(gs[4, 0])
    if len(z):
        lim = max(4.0, min(float(np.max(np.abs(z))), 8.0))
        bins = np.linspace(-lim, lim, 41)
        ax.hist(np.clip(z, -lim, lim), bins=bins, density=True, color="#1f5fbf", alpha=0.6,
                label=f"error / sigma, {len(z)} values")  # fmt: skip
        x = np.linspace(-lim, lim, 300)
        ax.plot(x, np.exp(-0.5 * x**2) / np.sqrt(2 * np.pi), "k", lw=1.2, label="N(0, 1)")
        ax.legend(fontsize=8)
    ax.set_xlabel("error / sigma (all axes)")
    ax.set_title("is the sigma honest? the histogram should follow N(0, 1)")
    beyond3 = float(np.mean(np.abs(z) > 3)) if len(z) else float("nan")
    beyond5 = int(np.sum(np.abs(z) > 5))
    ax = fig.add_subplot(gs[4, 1])
    ax.axis("off")
    lines = [f"{int(ok.sum())} of {len(ok)} rows ok"]
    lines += [f"{_label(n)}: RMS error {rms[n]:.4g}" for n in names if rms[n] is not None]
    if len(z):
        lines += [f"beyond 3 sigma: {100 * beyond3:.2f} % (a Gaussian: 0.27 %)",
                  f"beyond 5 sigma: {beyond5}"]  # fmt: skip
    ax.text(0.02, 0.95, "\n".join(lines), va="top", family="monospace", fontsize=10)
    return {"rms": rms, "beyond_3sigma_share": beyond3, "beyond_5sigma": beyond5}

"""A live run kept as a recording (`track --record DIR`) that `batch DIR` replays to the
run's own rows.

DIR holds, losslessly:

- ``frame_NNNNNN.png`` and ``times.csv``: every frame the run processed, with its time,
  its absolute time, its number in the run and whether it was read late (the folder
  source reads them back: visvec.sources.folder);
- ``rig.toml`` and ``calibration_N.toml``: copies of the rig and calibration files the
  run used, and ``recording.json``: what was run (command, visvec's version, source,
  whether an IMU was fused);
- ``rows.csv``: the run's rows (with an IMU: the fused rows), ``camera.csv``: with an
  IMU, the camera's own rows;
- with an IMU, ``events.jsonl``: every event the fusion loop took, in order, and when
  (visvec.fuse.live.EventLog: the IMU's rows as they arrived, the camera's fixes by
  frame number and exposure, the idle ticks), and ``imu.csv``: the IMU's rows as they
  came, for other tools.

A replay processes the frames again (the camera's rows are the run's: the same frames
at the same times through the same pipeline), and with an IMU gives the fusion loop the
recorded events at the moments they were taken, so the fused rows are the run's too,
every column but latency_ms.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import sys
from pathlib import Path

from visvec import __version__

MANIFEST = "recording.json"
EVENTS = "events.jsonl"


def is_recording(folder: str | Path) -> bool:
    """Whether ``folder`` is a `track --record` recording."""
    return (Path(folder) / MANIFEST).is_file()


def start(folder: str | Path, rig_path: str, calibrations: tuple[str, ...], source: str,
          imu: str | None) -> None:  # fmt: skip
    """The recording's folder (made; the caller has refused one that holds a recording)
    with the copies of the rig and calibration files and its manifest."""
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(rig_path, d / "rig.toml")
    cals = []
    for k, c in enumerate(calibrations, start=1):
        shutil.copyfile(c, d / f"calibration_{k}.toml")
        cals.append(f"calibration_{k}.toml")
    (d / MANIFEST).write_text(json.dumps({
        "visvec": __version__,
        "command": sys.argv,
        "source": source,
        "rig": {"file": "rig.toml", "from": str(rig_path)},
        "calibration": [{"file": f, "from": str(c)} for f, c in zip(cals, calibrations,
                                                                    strict=True)],
        "imu": imu,
    }, indent=2) + "\n")  # fmt: skip


def manifest(folder: str | Path) -> dict:
    return json.loads((Path(folder) / MANIFEST).read_text())


def differences(folder: str | Path, rig_path: str, calibrations: tuple[str, ...]) -> list[str]:
    """What a replay's rig and calibration files change against the recorded ones (an
    empty list: the same files, byte for byte)."""
    d = Path(folder)
    m = manifest(d)
    out = []
    if Path(rig_path).read_bytes() != (d / m["rig"]["file"]).read_bytes():
        out.append(f"the rig {rig_path} is not the one recorded ({d / m['rig']['file']})")
    rec = [d / c["file"] for c in m["calibration"]]
    if len(rec) != len(calibrations) or any(
        Path(a).read_bytes() != b.read_bytes() for a, b in zip(calibrations, rec, strict=False)
    ):
        given = ", ".join(calibrations) or "none"
        kept = ", ".join(str(p) for p in rec) or "none"
        out.append(f"the calibration files ({given}) are not the ones recorded ({kept})")
    return out


def write_imu_csv(folder: str | Path) -> int:
    """``imu.csv`` from the recorded events: the IMU's rows as they came (the columns
    of the first). The number of rows."""
    from visvec.fuse.live import read_event_log

    d = Path(folder)
    rows = [e["row"] for e in read_event_log(d / EVENTS) if e["k"] == "imu" and "row" in e]
    if not rows:
        return 0
    cols = list(rows[0])
    with open(d / "imu.csv", "w", encoding="utf-8") as fh:
        fh.write(",".join(cols) + "\n")
        for r in rows:
            fh.write(",".join(str(r.get(c, "")) for c in cols) + "\n")
    return len(rows)


@contextlib.contextmanager
def rows_file(path: str | Path, columns):
    """A CSV sink of ``columns`` at ``path`` inside the recording (its rows.csv,
    camera.csv), flushed row by row, closed at the end."""
    from visvec.sinks.writers import CsvSink

    with open(path, "w", newline="", encoding="utf-8") as fh:
        yield CsvSink(fh, columns)

"""Writing the small TOML files visvec produces (calibration files)."""

from __future__ import annotations

import math
from collections.abc import Mapping


def _value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return '"nan"'
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if hasattr(v, "tolist"):
        v = v.tolist()
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dumps(sections: Mapping[str, Mapping[str, object]], header: str = "") -> str:
    """TOML text of {section: {key: value}}; ``header`` lines become comments."""
    lines = [f"# {h}" if h else "#" for h in header.splitlines()]
    for name, table in sections.items():
        if lines:
            lines.append("")
        lines.append(f"[{name}]")
        arrays = {
            k: v
            for k, v in table.items()
            if isinstance(v, list) and v and all(isinstance(t, Mapping) for t in v)
        }
        for k, v in table.items():
            if k not in arrays:
                lines.append(f"{k} = {_value(v)}")
        for k, tables in arrays.items():  # arrays of tables: [[name.key]]
            for t in tables:
                lines += ["", f"[[{name}.{k}]]"]
                lines += [f"{kk} = {_value(vv)}" for kk, vv in t.items()]
    return "\n".join(lines) + "\n"

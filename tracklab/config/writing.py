"""TOML text for the shapes experiment files use (a tuned experiment written back)."""

from __future__ import annotations

import json
import re

import numpy as np


def dump_toml(doc: dict) -> str:
    """A TOML text for the shapes experiment files use (tables, arrays of tables, scalars, lists)."""

    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, np.integer)):
            return str(int(v))
        if isinstance(v, (float, np.floating)):
            return repr(float(v))
        if isinstance(v, str):
            return json.dumps(v, ensure_ascii=False)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        raise TypeError(f"cannot write {type(v).__name__} to TOML")

    def key(k):
        return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k, ensure_ascii=False)

    def table(name, t, out):
        scalars = {k: v for k, v in t.items() if not isinstance(v, dict) and not is_table_list(v)}
        out.append(f"[{name}]")
        out += [f"{key(k)} = {value(v)}" for k, v in scalars.items()]
        out.append("")
        for k, v in t.items():
            if isinstance(v, dict):
                table(f"{name}.{key(k)}", v, out)

    out = []
    for k, v in doc.items():
        if isinstance(v, dict):
            table(k, v, out)
        elif is_table_list(v):
            for item in v:
                out.append(f"[[{k}]]")
                out += [f"{key(kk)} = {value(vv)}" for kk, vv in item.items()]
                out.append("")
        else:
            out.insert(0, f"{k} = {value(v)}")
    return "\n".join(out)


def is_table_list(v):
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)

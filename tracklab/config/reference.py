"""The reference of every kind an experiment file may name, as Markdown, from the declarations
themselves (``tracklab list --markdown``; the documentation's kinds page is its output, and a
test keeps the two equal, so the reference cannot drift from the code)."""

from __future__ import annotations


def _default(p) -> str:
    d = p.default
    if callable(d):
        return "from the context"
    if d is None:
        return "—"
    return f"[{', '.join(f'{v:g}' for v in d)}]" if isinstance(d, tuple) else f"{d:g}"


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _table(params: dict, options: dict | None = None) -> list[str]:
    """A kind's numbers (and structural options) as a Markdown table."""
    if not params and not options:
        return ["No numbers of its own.", ""]
    rows = ["| field | unit | default | tune | sweep | what it is |", "|---|---|---|---|---|---|"]
    for name, p in params.items():
        rows.append(f"| `{name}` | {_cell(p.unit) or '—'} | {_default(p)} | {'yes' if p.tune else ''} | "
                    f"{'scale' if p.sweep else ''} | {_cell(p.doc)} |")
    for name, o in (options or {}).items():
        allowed = " \\| ".join(f"`{c}`" for c in o.choices) if getattr(o, "choices", None) else f"{o.lo}…{o.hi}"
        rows.append(f"| `{name}` | — | `{o.default!r}` | | | structure: {allowed} |")
    return rows + [""]


SENSOR_COMMON = (
    ("name", "", "the kind", "the sensor's name, which a filter's `sensors` list names"),
    ("p_detect", "", "1", "probability that the target is detected at a report (a miss is a predict-only step)"),
    ("period", "s", "`dt`", "time between reports, a whole multiple of `dt`"),
    ("offset", "s", "0", "time of the first report, a whole multiple of `dt`"),
    ("clutter_density", "per unit volume of the measurement space", "—",
     "false alarms per unit volume (per m² for a Cartesian sensor, per m·rad for a polar one): the scans hold "
     "clutter; needs `[track_loss]` and an association filter"),
    ("clutter_window", "the sensor's units", "—", "the clutter's region: ± these half-widths about the target's "
     "noise-free measurement, one per component"),
    ("clutter_coverage", "the sensor's units", "—", "or a fixed box, `[[lo, hi], …]` per component"),
    ("max_returns", "", "16", "a scan's capacity (structure); a scan with more returns is counted as overflowed"),
    ("snr", "dB", "—", "the target's mean SNR (Swerling I): the returns carry amplitudes and a scan's rows are in "
     "order of amplitude (the strongest neighbour needs it)"),
)


def kinds_markdown() -> str:
    """The whole reference: filter kinds, sensors (with the fields every sensor has), scenarios,
    airborne-radar trackers and servo estimators."""
    from tracklab.filters.registry import KINDS
    from tracklab.scenarios import SCENARIOS
    from tracklab.sensors import SENSORS
    from tracklab.worlds.airborne.registry import TRACKERS
    from tracklab.worlds.servo.registry import ESTIMATORS

    out = ["# Kinds and their numbers", "",
           "Every kind an experiment file may name, with the numbers it declares: their unit, default, whether "
           "`tracklab tune --params` may tune them and whether a sweep's scale factor (`--grid NAME=LO:HI:N`) may "
           "multiply them. Any number of a file also sweeps by its path (`--grid sensor.sigma_r=50:200:7`). "
           "This page is generated from the declarations (`tracklab list --markdown`).", ""]
    out += ["## Filters (`[[filter]]`)", ""]
    for k in KINDS.values():
        out += [f"### `{k.name}`", "", f"{k.doc[0].upper()}{k.doc[1:]}. Sensors: {', '.join(f'`{a}`' for a in k.accepts)}.",
                ""] + _table(dict(k.params))
    out += ["A kind `\"package.module:factory\"` is a filter of your own: `factory(context, **the table's other "
            "keys)` returns a `Filter`, and the numbers it declares with `tracklab.declare` are its fields "
            "([Your own filter](own-filter.md)).", ""]
    out += ["## Sensors (`[sensor]`, `[[sensor]]`)", "", "Every sensor has these fields:", "",
            "| field | unit | default | what it is |", "|---|---|---|---|"]
    out += [f"| `{n}` | {u or '—'} | {d} | {w} |" for n, u, d, w in SENSOR_COMMON] + [""]
    for k in SENSORS.values():
        out += [f"### `{k.name}`", "", f"{k.doc[0].upper()}{k.doc[1:]}.", ""] + _table(dict(k.params))
    out += ["## Scenarios (`[scenario]`)", ""]
    for k in SCENARIOS.values():
        out += [f"### `{k.name}`", "", f"{k.doc[0].upper()}{k.doc[1:]}.", ""] + _table(dict(k.params))
    out += ["## Airborne-radar trackers (`[[tracker]]` of an `[airborne]` file, paper 001)", ""]
    for k in TRACKERS.values():
        rows = _table(dict(k.params))
        if k.choices:
            rows = rows[:-1] + [f"Choices: {', '.join(f'`{n}` = ' + ' | '.join(f'`{v}`' for v in c) for n, c in k.choices.items())}.", ""]
        out += [f"### `{k.name}`", "", f"{k.doc[0].upper()}{k.doc[1:]}.", ""] + rows
    out += ["## Servo estimators (`[[estimator]]` of a `[servo]` file, paper 003)", ""]
    for k in ESTIMATORS.values():
        out += [f"### `{k.name}`", "", f"{k.doc[0].upper()}{k.doc[1:]}.", ""] + _table(dict(k.params), dict(k.options))
    return "\n".join(out).rstrip() + "\n"

"""Every figure kind, drawn from the statistics documents in results/ (and a small sweep): no text
outside the canvas, every filter in the legend, time axes and value axes labelled with their
units, and what the notes say is what is drawn."""

from pathlib import Path

import numpy as np
import pytest

from tracklab.report import airborne, figures, servo, sweep
from tracklab.report.document import read_results

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"


@pytest.fixture
def drawn(monkeypatch):
    """The figures the report modules save, by file stem, kept open (nothing written)."""
    out = {}

    def keep(plt, fig, folder, stem, formats=("png",)):
        out[stem] = fig

    for module in (figures, airborne, servo, sweep):
        monkeypatch.setattr(module, "save", keep)
    yield out
    import matplotlib.pyplot as plt

    plt.close("all")


def _texts(fig):
    from matplotlib.text import Text

    return [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]


def _check(fig, stem, labels):
    """Nothing outside the canvas; every axis that draws labelled; the legend names every filter."""
    fig.canvas.draw()
    box = fig.get_tightbbox(fig.canvas.get_renderer())  # of everything drawn, in inches
    w, h = fig.get_size_inches()
    assert box.x0 >= -0.02 and box.y0 >= -0.02 and box.x1 <= w + 0.02 and box.y1 <= h + 0.02, (stem, box, (w, h))
    drawing = [ax for ax in fig.axes if ax.lines or ax.collections or ax.images]
    for ax in drawing:
        if ax.get_label() == "<colorbar>":
            continue
        shared = fig._supylabel.get_text() if getattr(fig, "_supylabel", None) else ""  # one label for a column
        named = ax.get_ylabel() + ax.get_title() + ax.get_title(loc="left") + shared
        assert named.strip(), (stem, "an axis with no name")
    legend_text = " ".join(t.get_text() for lg in fig.legends + [ax.get_legend() for ax in fig.axes if ax.get_legend()]
                           for t in lg.get_texts())
    titles = " ".join(ax.get_title() for ax in fig.axes)
    for label in labels:
        assert label in legend_text or label in titles, (stem, label)


def _doc(name):
    return read_results(RESULTS / name)


@pytest.mark.parametrize("name, expected", [
    ("lidar_crossing", {"rmse", "rmse_axes", "mean_error", "nees", "nis", "pred_error", "error_cdf", "run0",
                        "run0_error", "track"}),
    ("clutter_cv", {"track_loss", "rmse", "run0"}),  # tracking in clutter
])  # (named prediction windows: the next test, on paper 004's overflight)
def test_tracking_figures(drawn, name, expected):
    doc = _doc(name)
    figures.plot_figures(doc, Path("unused"))
    assert expected <= set(drawn), sorted(drawn)
    for stem, fig in drawn.items():
        _check(fig, stem, list(doc["filters"]))  # the track's panels name their filters in their titles
        if stem.startswith(("rmse", "mean_error", "nees", "nis", "pred_error", "run0", "track_loss")):
            assert any("time (s)" in ax.get_xlabel() for ax in fig.axes), stem
    if "track" in drawn:  # one colour scale, named with its unit; coinciding filters share a panel
        bars = [ax for ax in drawn["track"].axes if ax.get_label() == "<colorbar>"]
        assert len(bars) == 1 and bars[0].get_ylabel() == "position RMSE (m)"
        panels = [ax for ax in drawn["track"].axes if ax.collections and ax not in bars]
        assert len(panels) < len(doc["filters"]) or name != "lidar_crossing"
    rmse = drawn["rmse"]
    ylabels = [ax.get_ylabel() for ax in rmse.axes]
    pu, vu = doc.get("units", ("m", "m/s"))
    assert f"RMSE position ({pu})" in ylabels and f"RMSE velocity ({vu})" in ylabels, ylabels
    note = " ".join(" ".join(t.get_text() for lg in rmse.legends for t in lg.get_texts()).split())
    a, b = doc["window"]
    assert f"steps {a}–{b}" in note and "brackets" not in note  # what the numbers under each name are
    if doc.get("track_loss"):
        assert "runs never lost" in note and "PCRLB in clutter" in note


def test_named_windows_and_manoeuvres_are_shaded_and_named(drawn):
    doc = _doc("error_space_overflight")
    figures.plot_figures(doc, Path("unused"))
    names = {t.get_text() for t in _texts(drawn["pred_error"])}
    assert "60-90 s" in names
    for stem in ("pred_error", "rmse"):
        _check(drawn[stem], stem, list(doc["filters"]))
    doc["experiment"]["scenario"] = {"kind": "manoeuvre", "segments": [{"duration": 30.0},
                                                                      {"duration": 20.0, "turn_g": 4.0}]}
    assert figures.manoeuvre_spans(doc) == {"4 g turn": [30.0, 50.0]}
    t = np.arange(1.0, 101.0)
    v = np.where((t > 40) & (t < 45), 100.0, 1.0)
    assert figures.clipped_spans(t, v, 10.0) == "t = 41–44 s"


def test_airborne_and_servo_figures(drawn):
    doc = _doc("airborne_radar")
    airborne.plot_airborne(doc, Path("unused"))
    assert {"pointing_error", "rate_error", "range_error", "nees", "error_cdf"} <= set(drawn)
    with_nees = [l for l, f in doc["filters"].items() if np.isfinite(figures.arr(f["series"]["nees"])).any()]
    for stem, fig in drawn.items():
        _check(fig, stem, with_nees if stem == "nees" else list(doc["filters"]))
    named = {t.get_text() for t in _texts(drawn["pointing_error"])}
    assert set(doc["windows"]) <= named, named  # the report windows shaded and named, the jolt's among them
    note = " ".join(" ".join(t.get_text() for lg in drawn["pointing_error"].legends for t in lg.get_texts()).split())
    assert "disturbance 12–14 s" in note and "jolted 10 mrad at 12 s" in note, note
    drawn.clear()
    doc = _doc("dekf_on_axis")
    servo.plot_servo(doc, Path("unused"))
    assert {"tracking_error", "error_cdf"} <= set(drawn)
    for stem, fig in drawn.items():
        _check(fig, stem, [])


def test_sweep_figures_share_an_axis_and_a_colour_scale_and_mark_the_matched_point(drawn, tmp_path):
    """A 1-D sweep draws every filter on one axis; a 2-D sweep's heatmaps share one colour scale,
    label each cell with its value and mark the matched point (every scale factor 1)."""
    from tracklab.config import load_experiment
    from tracklab.config.paths import parse_grid
    from tracklab.studies.sweep import sweep as run_sweep
    from test_intervals import LINEAR

    path = tmp_path / "exp.toml"
    path.write_text(LINEAR + '\n[[filter]]\nkind = "kf"\nlabel = "KF high q"\naccel_sigma = 6.0\n')
    exp = load_experiment(path)
    labels = [f.label for f in exp.filters]
    for grid in (["q=0.1:10:3"], ["q=0.1:10:3", "r=0.5:2:3"]):
        drawn.clear()
        doc = run_sweep(exp, [parse_grid(g) for g in grid], runs=20)
        sweep._plot({**doc, "name": exp.name}, list(doc["axes"]), labels, tmp_path)
        fig = drawn["sweep_rmse_pos"]
        _check(fig, f"sweep {grid}", labels)
        if len(grid) == 1:
            assert len([ax for ax in fig.axes if ax.lines]) == 1  # one shared axis
        else:
            meshes = [c for ax in fig.axes for c in ax.collections if hasattr(c, "norm") and c.get_array() is not None]
            assert len({(m.norm.vmin, m.norm.vmax) for m in meshes}) == 1  # one colour scale
            cells = [t.get_text() for ax in fig.axes for t in ax.texts]
            assert len(cells) == 3 * 3 * len(labels)
            assert any("matched point" in t.get_text() for t in _texts(fig))
            assert any(ax.get_label() == "<colorbar>" and "RMSE" in ax.get_ylabel() for ax in fig.axes)

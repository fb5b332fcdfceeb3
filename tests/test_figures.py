"""Figures people can read: every method in its own style in every panel, the legend outside the
axes, a method without work counts named as such, stability bars inside their scene's slot."""

import numpy as np
import pandas as pd
import pytest

from reelbench.benchmark.figures import plots
from reelbench.benchmark.studies import stability_report
from reelbench.benchmark.figures.styles import style


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot layer would save, kept open for inspection."""
    seen = []

    def keep(fig, path, dpi=110):
        fig.canvas.draw()
        seen.append(fig)
        return path

    monkeypatch.setattr(plots, "save_figure", keep)
    monkeypatch.setattr(stability_report, "save_figure", keep)
    yield seen
    for fig in seen:
        plots.plt.close(fig)


def _runs():
    rows = []
    for name, work in (("lgvi", 1.0), ("tsit5", 3.0), ("kvaerno5", np.nan), ("my_plugin", 2.0)):
        for k, dt in enumerate((0.01, 0.005, 0.0025)):
            adaptive = name == "kvaerno5"
            rows.append({"scene": "s", "integrator": name, "setting": f"rtol=1e-{k + 4}" if adaptive else f"dt={dt:g}",
                         "dt": np.nan if adaptive else dt, "rtol": 10.0 ** -(k + 4) if adaptive else np.nan,
                         "status": "ok", "run_time": 1e-3 * (k + 1) * (1 + work if work == work else 5),
                         "work_evals": work * 100 * 3 ** k, "energy_error": 1e-4 / 4 ** k,
                         "position_error_final": 1e-5 / 4 ** k, "position_error_max": 2e-5 / 4 ** k})
    rows.append({**rows[0], "setting": "dt=0.02", "dt": 0.02, "status": "diverged", "energy_error": np.nan})
    return pd.DataFrame(rows)


def _outside(fig, legend) -> bool:
    box = legend.get_window_extent()
    return all(box.x0 >= ax.get_window_extent().x1 for ax in fig.axes)


def test_work_precision_styles_legend_outside_and_a_method_without_work_counts(figures):
    plots.work_precision(_runs(), "s", "unused")
    (fig,) = figures
    (legend,) = fig.legends
    labels = [t.get_text() for t in legend.get_texts()]
    # drawn in the top row: one legend entry, and the caption says the bottom row lacks it
    assert "kvaerno5 (adaptive)" in labels and not any(lb.startswith("kvaerno5:") for lb in labels)
    assert "no work count for kvaerno5" in fig._suptitle.get_text()
    assert {"lgvi (fixed dt)", "tsit5 (fixed dt)", "my_plugin (fixed dt)"} <= set(labels)
    assert _outside(fig, legend)
    top, bottom = fig.axes[:3], fig.axes[3:]
    for ax in top + bottom:  # each method's colour is its own, in the top and the bottom row alike
        colours = {line.get_color() for line in ax.get_lines()}
        assert {style("lgvi").color, style("tsit5").color, style("my_plugin").color} <= colours
    assert all(style("kvaerno5").color in {line.get_color() for line in ax.get_lines()} for ax in top)
    assert all(style("kvaerno5").color not in {line.get_color() for line in ax.get_lines()} for ax in bottom)
    assert "1 runs failed" in fig._suptitle.get_text()


def test_the_bottom_row_is_work_in_flops_the_unit_methods_are_ranked_by(figures):
    """With a ``flops`` column the bottom row plots it (not the sum of unlike counts ``work_evals``)."""
    runs = _runs()
    flops = runs["work_evals"] * 7.0 + np.where(runs["integrator"] == "lgvi", 5e4, 0.0)  # not a multiple of work_evals
    plots.work_precision(runs.assign(flops=flops), "s", "unused")
    (fig,) = figures
    bottom = fig.axes[3:]
    assert all(ax.get_xlabel() == "work (floating-point operations)" for ax in bottom)
    ok = runs["status"] == "ok"
    lgvi = sorted(flops[ok & (runs["integrator"] == "lgvi")])
    colour = style("lgvi").color
    assert any(sorted(line.get_xdata()) == lgvi for ax in bottom for line in ax.get_lines() if line.get_color() == colour)
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "kvaerno5 (adaptive)" in labels and "no flops count for kvaerno5" in fig._suptitle.get_text()
    assert "floating-point operations" in fig._suptitle.get_text() and "Newton" not in fig._suptitle.get_text()


def test_tick_labels_of_a_panel_do_not_overlap(figures):
    plots.work_precision(_runs(), "s", "unused")
    (fig,) = figures
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        for axis, lo, hi in ((ax.xaxis, "x0", "x1"), (ax.yaxis, "y0", "y1")):
            frame = ax.get_window_extent(renderer)
            shown = [t for t in axis.get_ticklabels(which="both") if t.get_visible() and t.get_text()]
            boxes = sorted((t.get_window_extent(renderer) for t in shown), key=lambda b: getattr(b, lo))
            # the labels of ticks inside the panel (major and minor), in order along the axis
            boxes = [b for b in boxes if getattr(b, hi) >= getattr(frame, lo) and getattr(b, lo) <= getattr(frame, hi)]
            for a, b in zip(boxes, boxes[1:]):
                assert getattr(a, hi) <= getattr(b, lo), [t.get_text() for t in shown]


def test_stability_bars_stay_inside_their_scenes_slot(figures):
    scenes = ["a", "b", "c"]
    names = ["lgvi", "lgvi_sym", "lgvi_yoshida4", "lgvi_suzuki4", "tsit5", "p1", "p2"]
    rows = [{"scene": s, "integrator": n, "kind": "fixed", "largest_stable_dt": 0.005, "status": "ok", "bounded": True,
             "steps": 100.0, "t_reached": 1.0} for s in scenes for n in names]
    rows += [{"scene": s, "integrator": n, "kind": "adaptive", "largest_stable_dt": np.nan, "status": "ok",
              "bounded": True, "steps": 100.0, "t_reached": 1.0} for s in scenes for n in ("rk45", "dop853")]
    stability_report.plot(pd.DataFrame(rows), "unused")
    (fig,) = figures
    bars = [p for p in fig.axes[0].patches if p.get_height() > 0]
    assert len(bars) == len(scenes) * len(names)
    for bar in bars:
        slot = round(bar.get_x() + bar.get_width() / 2)
        assert slot - 0.5 < bar.get_x() and bar.get_x() + bar.get_width() < slot + 0.5
        assert bar.get_facecolor()[:3] == pytest.approx(
            tuple(int(style_hex, 16) / 255 for style_hex in _rgb(bar, names, scenes)), abs=1e-6)
    assert _outside(fig, fig.legends[0])


def _rgb(bar, names, scenes):
    """The hex pairs of the style colour of the method a bar belongs to (bars are drawn method by method)."""
    k = bar.axes.patches.index(bar) // len(scenes)
    h = style(names[k]).color.lstrip("#")
    return h[0:2], h[2:4], h[4:6]


def test_the_energy_panel_draws_every_effects_potential_so_the_parts_add_up(figures):
    """towed_offset lists buoyancy: its potential is a diagnostics column of its own (V_buoyancy)
    and a line of the paper figure's energy panel (b), and T + V_gravity + V_elastic + V_buoyancy = E."""
    from reelbench.integrators import Trajectory
    from reelbench.models import build_model, load_scene
    from reelbench.models.diagnostics import evaluate

    scene = load_scene("towed_offset", elements=2, t_end=0.1)
    x, R, w = build_model(scene).initial_state()
    traj = Trajectory(t=np.array([0.0, 0.1]), x=np.array([x, x + 0.01]), attitude=np.array([R, R]),
                      attitude_kind="matrix", velocity=np.array([w, w + 0.1]), work=np.zeros(2), integrator="made")
    df = evaluate(scene, traj)
    assert "V_buoyancy" in df
    parts = df["kinetic"] + df["V_gravity"] + df["V_elastic"] + df["V_buoyancy"]
    np.testing.assert_allclose(parts, df["energy"], rtol=1e-14, atol=1e-12)
    plots.paper_panels(scene, traj, df, "unused.png")
    (fig,) = figures
    labels = [line.get_label() for line in fig.axes[1].get_lines()]
    assert {"E", "T", "V_gravity", "V_elastic", "V_buoyancy"} <= set(labels), labels

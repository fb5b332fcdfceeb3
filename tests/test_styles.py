"""reelbench.benchmark.figures.styles: one look per method, from its name only; legends outside the data; a method
a panel cannot draw is listed with the reason."""

import os
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from reelbench.benchmark.figures.styles import (PLUGIN_COLOURS, SHIPPED, clashes, legend_entries, legend_outside, style,  # noqa: E402
                              styles)

NAMES = st.text("abcdefghijklmnopqrstuvwxyz0123456789_", min_size=1, max_size=20)


def test_every_shipped_and_registered_method_has_its_own_colour_and_marker():
    from reelbench.integrators import available

    from reelbench.integrators import get_integrator

    registered = [n for n in available() if not n.startswith("test_")]
    assert set(SHIPPED) <= set(registered), "a shipped style for a method that is no longer registered"
    ours = [n for n in registered if type(get_integrator(n)).__module__.startswith("reelbench.integrators.")]
    assert set(ours) <= set(SHIPPED), "a method of this repository drawn in a plugin's hashed look"
    assert clashes([*SHIPPED, *registered]) == []
    # among the shipped ones colour and marker each tell the methods apart alone
    assert len({s.color for s in SHIPPED.values()}) == len({s.marker for s in SHIPPED.values()}) == len(SHIPPED)


@settings(max_examples=100, deadline=None)
@given(st.lists(NAMES, max_size=8, unique=True), NAMES)
def test_a_style_does_not_change_when_another_method_is_added(names, new):
    before = styles(names)
    after = styles([new, *names])
    assert all(after[n] == before[n] for n in names)
    assert new in SHIPPED or style(new).color in PLUGIN_COLOURS  # a plugin never takes a shipped colour


def test_a_plugin_style_is_the_same_in_another_process():
    # a hash of the name, not Python's per-process hash(): worker processes draw the same figure
    names = ["my_method", "splitting2", "rk4_fixed"]
    code = ("from reelbench.benchmark.figures.styles import style; "
            f"print([tuple(style(n).__dict__.values()) for n in {names!r}])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONHASHSEED": "12345"}).stdout.strip()
    assert out == repr([tuple(style(n).__dict__.values()) for n in names])


def test_clashes_are_reported():
    a = "my_method"
    twin = next(f"m{k}" for k in range(10_000) if (style(f"m{k}").color, style(f"m{k}").marker)
                == (style(a).color, style(a).marker))
    assert clashes([a, twin, "lgvi"]) == [tuple(sorted((a, twin)))]


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="non-empty string"):
        style("")
    with pytest.raises(ValueError, match="sweep must be 'dt' or 'rtol'"):
        style("lgvi").kwargs("adaptive")
    with pytest.raises(ValueError, match="3 handles for 2 labels"):
        legend_outside(plt.figure(), [None] * 3, ["a", "b"])


def test_a_figure_keeps_each_method_look_across_panels_and_lists_the_one_it_cannot_draw():
    # two rows as in the work-precision figure: kvaerno5 has no work count, so the bottom row lacks it
    curves = {("lgvi", "dt"): [1, 2, 4], ("tsit5", "dt"): [2, 3, 5], ("tsit5", "rtol"): [3, 4, 6],
              ("dop853", "rtol"): [5, 6, 8], ("kvaerno5", "rtol"): [4, 8, 9]}
    fig, (top, bottom) = plt.subplots(2, 1)
    for (name, sweep), x in curves.items():
        top.loglog(x, [1e-3, 1e-5, 1e-7], **style(name).kwargs(sweep))
        if name != "kvaerno5":
            bottom.loglog(x, [1e-3, 1e-5, 1e-7], **style(name).kwargs(sweep))
    handles, labels = legend_entries(curves, absent={"kvaerno5": "no work count (bottom row)"})
    legend = legend_outside(fig, handles, labels)
    fig.canvas.draw()

    colour = {ln.get_color() for ln in top.lines[1:3]}
    assert colour == {style("tsit5").color}  # one method, one colour, both sweeps
    assert [ln.get_color() for ln in bottom.lines] == [style(n).color for n, _ in curves if n != "kvaerno5"]
    assert [ln.get_markerfacecolor() for ln in top.lines[1:3]] != [None, None]
    assert top.lines[1].get_markerfacecolor() != top.lines[2].get_markerfacecolor()  # fixed dt filled, adaptive hollow
    assert labels == ["dop853 (adaptive)", "kvaerno5 (adaptive)", "lgvi (fixed dt)", "tsit5 (fixed dt)",
                      "tsit5 (adaptive)", "kvaerno5: no work count (bottom row)"]
    box = legend.get_window_extent()
    for ax in fig.axes:
        assert not box.overlaps(ax.get_window_extent()), "the legend covers an axes"
    plt.close(fig)


def test_registered_plugins_never_share_a_look():
    """Two plugins whose names hash to the same colour and marker, both registered: the later
    one by name takes the next free look, so a figure of every registered method tells them
    apart (the unregistered names keep their hashed look)."""
    from reelbench.integrators import registry
    from reelbench.integrators.base import Integrator

    a = "my_method"
    twin = next(f"m{k}" for k in range(10_000) if (style(f"m{k}").color, style(f"m{k}").marker)
                == (style(a).color, style(a).marker))
    hashed = style(a)
    made = [type(f"Plugin_{n}", (Integrator,), {"name": n}) for n in (a, twin)]
    try:
        for cls in made:
            registry.register(cls)
        first, second = sorted((a, twin))
        assert style(first) == hashed if first == a else True
        assert (style(a).color, style(a).marker) != (style(twin).color, style(twin).marker)
        assert clashes(registry.available()) == []
    finally:
        for n in (a, twin):
            registry.unregister(n)
    assert style(a) == hashed  # unregistered again: the hashed look

"""Small things a user notices: progress lines, name suggestions, the `list` columns, and π3
where the physics does not conserve it."""

import dataclasses
import math

import numpy as np
import pandas as pd
import pytest

from reelbench.benchmark.cli.main import main


def test_progress_never_says_nan_seconds_left(monkeypatch):
    from reelbench.benchmark.core import engine

    clock = [0.0]
    monkeypatch.setattr(engine.time, "perf_counter", lambda: clock[0])
    lines = []
    progress = engine.Progress(4, cost=lambda i: math.nan if i else 1.0, log=lines.append)  # jobs without a prediction
    for i, row in enumerate(({"task_time": 2.0}, {"task_time": 1.0}, {})):
        clock[0] += 2.0
        progress.done(i, row)
    assert lines and not any("nan" in line for line in lines), lines
    assert "about 6 s left" in lines[0]  # the others count as the mean prediction: 3 x 1 in 2 s each


def test_a_misspelt_dotted_override_gets_the_nearest_name(capsys):
    assert main(["simulate", "fixed_length", "--dt", "0.01", "--set", "body.mas=2"]) == 2
    assert "unknown override 'body.mas' (did you mean 'body.mass'?)" in capsys.readouterr().err


def test_list_aligns_every_name_and_marks_the_extended_sweep(capsys):
    from reelbench.integrators import available

    assert main(["list"]) == 0
    out = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line for line in out if line.startswith("  ") and " order " in line}
    assert set(rows) == set(available())
    assert len({line.index(" order ") for line in rows.values()}) == 1  # one column, long names included
    from reelbench.benchmark.runs.sweep import EXTENDED_METHODS
    from reelbench.integrators import origin

    for name, line in rows.items():
        own = origin(name).own
        expect = ("extended" if name in EXTENDED_METHODS else "default") if own else "plugins"
        assert line.split()[3] == expect, line
    assert any(line.split()[3] == "extended" for line in rows.values())


def test_pi3_is_reported_only_where_the_physics_conserves_it(monkeypatch):
    from reelbench.benchmark.runs import metrics
    from reelbench.models import layout, load_scene
    from reelbench.models.effects import Effect, get_effect

    assert layout.StateLayout.from_scene(load_scene("retrieval")).conserves_pi3  # every shipped effect keeps it

    class Drag(Effect):  # an external force that does not declare it keeps π3
        name = "drag_test"
        forcing = True

    monkeypatch.setattr(layout, "get_effect", lambda e: Drag if e == "gravity" else get_effect(e))
    assert not layout.StateLayout.from_scene(load_scene("fixed_length")).conserves_pi3
    df = pd.DataFrame({"pi3": [1.0, 1.5, 0.7]})
    assert math.isnan(metrics._pi3_error(metrics.Evidence(df=df, has_work=True, conserves_pi3=False)))
    assert metrics._pi3_error(metrics.Evidence(df=df, has_work=True)) == pytest.approx(0.5)


def test_panel_d_drops_pi3_where_it_is_not_conserved(monkeypatch, tmp_path):
    import matplotlib.pyplot as plt

    from reelbench.benchmark.figures import plots
    from reelbench.integrators import get_integrator
    from reelbench.models import build_model, load_scene
    from reelbench.models.diagnostics import evaluate

    scene = load_scene("fixed_length", elements=2, t_end=0.1)
    traj = get_integrator("lgvi").solve(scene, dt=0.01)
    df = evaluate(scene, traj)
    titles = {}
    class Model:  # the scene's model, its layout saying whether π3 is conserved
        def __init__(self, model, conserved):
            self._model, self.layout = model, dataclasses.replace(model.layout, conserves_pi3=conserved)

        def __getattr__(self, name):
            return getattr(self._model, name)

    for conserved in (True, False):
        monkeypatch.setattr(plots, "build_model", lambda s, c=conserved: Model(build_model(s), c))
        shown = []
        monkeypatch.setattr(plots, "save_figure", lambda fig, path: shown.append(fig) or path)
        plots.paper_panels(scene, traj, df, tmp_path / "p.png")
        ax = shown[0].axes[-1]
        titles[conserved] = (ax.get_title(), [t.get_text() for t in ax.get_legend().get_texts()])
        plt.close("all")
    assert titles[True][0].startswith("(d) conserved quantities") and "|Δπ3| / |π3(0)|" in titles[True][1]
    assert "π3 not conserved" in titles[False][0] and "|Δπ3| / |π3(0)|" not in titles[False][1]
    assert np.isfinite(df["pi3"]).all()

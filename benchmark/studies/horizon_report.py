"""The energy study's report (`write`): its figure per scene (`energy_horizon`: the energy error
over a long horizon, what is left after the derived modified-energy offset, the axial vibration
and the least tension), drawn with the plot layer (`benchmark.figures.plots`), and for the
`energy` command its text (`benchmark.studies.properties.write_energy_section`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.lines import Line2D

from reelbench.benchmark.figures import styles
from reelbench.benchmark.studies.horizon import REFERENCE
from reelbench.benchmark.figures.plots import plt, save_figure, style_axes
from reelbench.benchmark.core.policy import setting_value
from reelbench.benchmark.studies.energy_drift import WINDOW_S, correction_of, is_symplectic, window_means
from reelbench.models.io import inside


def write(out: Path, rows: list[dict], scenes, text: bool = False) -> str:
    """The report of the energy study from its whole table (``rows``): energy_horizon_SCENE.png
    of each of this run's ``scenes`` that has rows (the others' figures are kept as they are),
    and with ``text`` the energy section of ``out``/README.md, or energy_horizon.md without one.
    Returns a line saying what it wrote."""
    from reelbench.benchmark.studies import horizon, properties

    out = Path(out)
    table = horizon.to_frame(rows)
    drawn = [energy_horizon(g, scene, out).name for scene, g in table.groupby("scene", sort=False)
             if scene in set(scenes)]
    wrote = ", ".join(f"{out}/{name}" for name in drawn)
    if text and len(table):
        readme = properties.write_energy_section(out)
        if readme is not None:
            wrote += f"{'; ' if wrote else ''}the energy section of {readme}"
    return f"wrote {wrote}" if wrote else ""


def listed(out: Path, scenes) -> list[tuple[str, str]]:
    """(file name, note) of the energy study's figures in ``out``, one per scene of its table:
    "" for this run's ``scenes``, "from an earlier run" for the others."""
    from reelbench.benchmark.studies import horizon

    path = Path(out) / horizon.TABLE
    try:
        table = horizon.read_earlier(pd.read_csv(path)) if path.is_file() else None
    except Exception:  # noqa: BLE001 - an unreadable table lists no figure
        return []
    if table is None or "scene" not in table:
        return []
    figures = (inside(out, f"energy_horizon_{scene}.png") for scene in dict.fromkeys(table["scene"]))
    return [(f.name, "" if f.name in {f"energy_horizon_{s}.png" for s in scenes} else "from an earlier run")
            for f in figures if f.is_file()]


def method_of(label: str) -> str:
    """The method name a label of the energy study starts with ("lgvi dt=0.005" -> "lgvi")."""
    return str(label).split(" ", 1)[0]


def energy_horizon(table: pd.DataFrame, scene: str, out_dir: Path) -> Path:
    """The energy study of one scene: one column per size N of the string, four rows against t,
    each a mean over windows of `benchmark.studies.energy_drift.WINDOW_S` s: (1) the change of E − E0
    since the first window; (2) what is left of it after the derived modified-energy offset
    −c_p h^p⟨P_p⟩ (`benchmark.studies.energy_drift`: P_2 = U''(v, v) of the string, P_4 = P4;
    `correction_of`; unchanged for a method without one);
    (3) the axial measure P/max T; (4) the least element tension (window minimum). One colour per
    method (`benchmark.figures.styles`), solid: its setting in the plan, dotted: the finer one; the accurate
    reference (`benchmark.studies.horizon.REFERENCE`) is drawn thick, under the others."""

    path = inside(out_dir, f"energy_horizon_{scene}.png")  # the scene name comes from a table: refused if it walks out
    sizes = sorted({int(n) for n in table["elements"]})
    fig, axes = plt.subplots(4, len(sizes), figsize=(6.4 * len(sizes), 12.5), squeeze=False, sharex=True)
    handles, labels = {}, {}
    col = lambda df, c: pd.to_numeric(df[c], errors="coerce").to_numpy(float) if c in df else np.full(len(df), np.nan)  # noqa: E731
    for j, n in enumerate(sizes):
        g = table[table["elements"].astype(int) == n]
        for name, m in g.groupby("integrator", sort=False):
            st = styles.style(name)
            ref = name == REFERENCE
            for k, (setting, h) in enumerate(sorted(m.groupby("setting", sort=False),
                                                    key=lambda kv: -setting_value(kv[0], missing=0.0))):
                h = h.sort_values("t")
                t, dev, P, G, P4, ten = (col(h, c) for c in ("t", "energy_dev", "axial_P", "geometric_G", "axial_P4",
                                                             "tension_min"))
                corr = correction_of(name, setting)
                x = (np.zeros_like(dev) if corr is None else
                     corr[2] ** corr[0] * (P + np.nan_to_num(G) if corr[0] == 2 else P4))
                cp = 0.0 if corr is None else corr[1]
                tc, d, xm, pm = window_means(t, dev, x, np.nan_to_num(P))
                if not len(tc):
                    continue
                tmin = np.array([np.nanmin(ten[(t >= c - WINDOW_S / 2) & (t < c + WINDOW_S / 2)]) for c in tc])
                kw = dict(color=st.color, linestyle="-" if k == 0 else ":", lw=2.6 if ref else 1.1,
                          alpha=0.45 if ref else 0.95, zorder=1 if ref else 2)
                r = d + cp * xm  # from the second window on: the first is the zero of both
                axes[0, j].semilogy(tc[1:], np.abs(d - d[0])[1:], **kw)
                axes[1, j].semilogy(tc[1:], np.abs(r - r[0])[1:], **kw)
                axes[2, j].semilogy(tc, np.maximum(pm, 1e-17), **kw)
                axes[3, j].plot(tc, tmin, **kw)
            handles[name] = Line2D([], [], color=st.color, lw=2.6 if ref else 1.1, alpha=0.45 if ref else 1.0)
            labels[name] = (f"{name} ({'symplectic' if is_symplectic(name) else 'not symplectic'}"
                            + (", the accurate reference)" if ref else ")"))
        axes[0, j].set_title(f"{scene}, N = {n}")
        style_axes(axes[0, j], ylabel=f"|⟨E − E0⟩ − first| / max T", legend=None)
        style_axes(axes[1, j], ylabel="after the offset −c_p h^p⟨P_p⟩", legend=None)
        style_axes(axes[2, j], ylabel="P = Σ EA l (dε/dt)² / max T (1/s²)", legend=None)
        style_axes(axes[3, j], xlabel="t (s)", ylabel="least tension (N)", legend=None)
        axes[3, j].axhline(0.0, color="k", lw=0.6)
    fig.suptitle(f"energy over a long horizon, {WINDOW_S:g}-s window means (solid: the plan's setting, dotted: "
                 "the finer one)\nrows: energy error; what is left after the modified-energy offset; axial vibration "
                 "P; least tension (< 0: compression)", fontsize=10)
    fig.tight_layout()
    fig.legend(list(handles.values()), list(labels.values()), loc="upper center", bbox_to_anchor=(0.5, 0.0),
               ncol=min(3, len(handles)), fontsize=8, frameon=False)  # below the panels: it hides none of them
    return save_figure(fig, path)

"""One fixed look per method for every figure: colour, marker and line style from its name.

A method's style depends on its name only, never on which other methods a figure draws or in
which order, so a method looks the same in every panel and every figure, and adding a plugin
changes nobody else's style. The shipped methods have hand-picked styles (`SHIPPED`), each with
its own colour (matplotlib's "tab10", colour-blind safer than the default cycle, then dark tones
far from it) and its own marker; line style by family (solid: the variational LGVIs, dashed: explicit
Runge–Kutta, dash-dot: implicit). Any other name gets a colour from a second palette (none of
the shipped colours) and a marker, both picked by a hash of the name (`style`). Registered
methods never share a look: a registered plugin whose hashed colour and marker another
registered plugin (earlier by name) already has takes the next free combination, so every
registered method is drawn distinctly, however many there are (distinct colour and marker for
up to `len(PLUGIN_COLOURS) * len(PLUGIN_MARKERS)` plugins, then distinct line styles too, up to
four times that). Only a name that is not registered can share a look with another (one chance
in `len(PLUGIN_COLOURS) * len(PLUGIN_MARKERS)` per pair); `clashes` lists such pairs so a figure
can say so.

How a sweep is drawn: filled markers for a fixed-step sweep (``dt``), hollow ones for an
adaptive sweep (``rtol``), so a method with both (``tsit5``) keeps its colour and marker.
Legends go outside the axes (`legend_outside`), and a method a figure cannot draw, e.g. one
without a work count on a work axis, stays in the legend with the reason (`legend_entries`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Iterable, Mapping

from matplotlib.lines import Line2D


@dataclass(frozen=True)
class Style:
    """How one method is drawn."""

    color: str
    marker: str
    linestyle: str

    def kwargs(self, sweep: str = "dt") -> dict:
        """Keyword arguments for ``Axes.plot``; ``sweep`` "rtol" draws hollow markers."""
        if sweep not in ("dt", "rtol"):
            raise ValueError(f"sweep must be 'dt' or 'rtol', got {sweep!r}")
        return {"color": self.color, "marker": self.marker, "linestyle": self.linestyle, "markersize": 6,
                "markerfacecolor": self.color if sweep == "dt" else "none", "markeredgecolor": self.color}


_VARIATIONAL, _EXPLICIT, _IMPLICIT = "-", "--", "-."

#: The methods this repository ships: distinct colours (tab10) and distinct markers.
SHIPPED: dict[str, Style] = {
    "lgvi": Style("#1f77b4", "o", _VARIATIONAL),  # blue
    "lgvi_sym": Style("#17becf", "s", _VARIATIONAL),  # cyan
    "lgvi_yoshida4": Style("#9467bd", "^", _VARIATIONAL),  # purple
    "lgvi_suzuki4": Style("#e377c2", "v", _VARIATIONAL),  # pink
    "tsit5": Style("#ff7f0e", "D", _EXPLICIT),  # orange
    "dop853": Style("#d62728", "X", _EXPLICIT),  # red
    "rk45": Style("#8c564b", "P", _EXPLICIT),  # brown
    "rk45_projected": Style("#bcbd22", "*", _EXPLICIT),  # olive
    "radau": Style("#2ca02c", "h", _IMPLICIT),  # green
    "kvaerno5": Style("#7f7f7f", "<", _IMPLICIT),  # grey
    # beyond tab10: dark tones far from its colours, and the remaining distinct markers
    "lie_rk4": Style("#008080", ">", _EXPLICIT),  # teal
    "crouch_grossman3": Style("#d4a000", "p", _EXPLICIT),  # gold
    "dopri5": Style("#000080", "d", _EXPLICIT),  # navy
    "dopri8": Style("#800000", "H", _EXPLICIT),  # maroon
    "rattle": Style("#000000", "8", _VARIATIONAL),  # black
}

#: Colours for any other method: dark and light tones not among the shipped ones.
PLUGIN_COLOURS = ("#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd", "#e6550d",
                  "#31a354", "#756bb1", "#636363", "#a55194")
PLUGIN_MARKERS = ("o", "s", "^", "v", "D", "p", ">", "d", "8", "H")
PLUGIN_LINESTYLES = (":", (0, (5, 1, 1, 1, 1, 1)), (0, (3, 1, 1, 1)), (0, (1, 1)))


#: every plugin look, colour and marker varying fastest: index i of a hash
_LOOKS = len(PLUGIN_COLOURS) * len(PLUGIN_MARKERS) * len(PLUGIN_LINESTYLES)


def _look(i: int) -> Style:
    i %= _LOOKS
    colour = PLUGIN_COLOURS[i % len(PLUGIN_COLOURS)]
    i //= len(PLUGIN_COLOURS)
    marker = PLUGIN_MARKERS[i % len(PLUGIN_MARKERS)]
    i //= len(PLUGIN_MARKERS)
    return Style(colour, marker, PLUGIN_LINESTYLES[i % len(PLUGIN_LINESTYLES)])


def _hashed(name: str) -> int:
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big") % _LOOKS


_registered_cache: dict[tuple, dict[str, Style]] = {}
_scanned = False


def _registered_looks() -> dict[str, Style]:
    """The registered plugins' looks, distinct: by name, each takes its hashed look, or the next
    one (by index) whose colour and marker no earlier plugin has (when all are taken: whose
    colour, marker and line style none has)."""
    global _scanned
    try:
        from reelbench.integrators import registry

        if not _scanned:  # the installed plugins, once (a scan of the entry points costs ~30 ms)
            registry.available()
            _scanned = True
        names = tuple(sorted(n for n in registry._REGISTRY if n not in SHIPPED))
    except Exception:  # no registry to read (a broken plugin environment): the hashed looks
        return {}
    if names not in _registered_cache:
        looks: dict[str, Style] = {}
        pairs, full = set(), set()
        for n in names:
            start = _hashed(n)
            cand = [_look(start + k) for k in range(_LOOKS)]
            pick = next((c for c in cand if (c.color, c.marker) not in pairs), None) \
                or next((c for c in cand if c not in full), cand[0])
            looks[n] = pick
            pairs.add((pick.color, pick.marker))
            full.add(pick)
        _registered_cache.clear()
        _registered_cache[names] = looks
    return _registered_cache[names]


def style(name: str) -> Style:
    """The style of method ``name``: `SHIPPED`'s; a registered plugin's, distinct from every
    other registered method's (`_registered_looks`); else one picked by a hash of the name
    (SHA-256, so the same on every machine and in every process)."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"style: a method name must be a non-empty string, got {name!r}")
    if name in SHIPPED:
        return SHIPPED[name]
    registered = _registered_looks().get(name)
    return registered if registered is not None else _look(_hashed(name))


def styles(names: Iterable[str]) -> dict[str, Style]:
    """name -> `style` for each name."""
    return {n: style(n) for n in names}


def clashes(names: Iterable[str]) -> list[tuple[str, str]]:
    """Pairs of ``names`` with the same colour and marker (a figure should say so)."""
    seen: dict[tuple[str, str], str] = {}
    out = []
    for n in sorted(set(names)):
        s = style(n)
        key = (s.color, s.marker)
        if key in seen:
            out.append((seen[key], n))
        else:
            seen[key] = n
    return out


from reelbench.benchmark.runs.sweep import SWEEP_WORDS  # noqa: E402  (one wording for labels and tables)


def legend_entries(drawn: Iterable[tuple[str, str]], absent: Mapping[str, str] | None = None
                   ) -> tuple[list[Line2D], list[str]]:
    """Legend handles and labels: one per (method, sweep) of ``drawn`` (sweep "dt" or "rtol"),
    sorted by name then sweep, and one per method of ``absent`` (method -> why it is missing,
    e.g. "no work count (bottom row)"), faded and labelled with the reason, even when another
    panel draws it — so no method is dropped from a figure silently."""
    handles, labels = [], []
    for name, sweep in sorted(set(drawn)):
        if sweep not in SWEEP_WORDS:
            raise ValueError(f"legend_entries: sweep must be 'dt' or 'rtol', got {sweep!r} for {name!r}")
        handles.append(Line2D([], [], **style(name).kwargs(sweep)))
        labels.append(f"{name} ({SWEEP_WORDS[sweep]})")
    for name, why in sorted((absent or {}).items()):  # also when drawn in another panel
        handles.append(Line2D([], [], **dict(style(name).kwargs("dt"), alpha=0.35)))
        labels.append(f"{name}: {why}")
    return handles, labels


def legend_outside(fig, handles: list, labels: list[str], *, fontsize: float = 8):
    """One legend for the whole figure, to the right of all its axes (none of its data hidden);
    save with ``bbox_inches="tight"`` so it stays in the picture."""
    if len(handles) != len(labels):
        raise ValueError(f"legend_outside: {len(handles)} handles for {len(labels)} labels")
    fig.canvas.draw()  # the axes' final positions (tight/constrained layouts move them)
    right = max((ax.get_position().x1 for ax in fig.axes), default=0.9)
    return fig.legend(handles, labels, loc="upper left", bbox_to_anchor=(right + 0.01, 0.98),
                      bbox_transform=fig.transFigure, fontsize=fontsize, frameon=False, borderaxespad=0.0)

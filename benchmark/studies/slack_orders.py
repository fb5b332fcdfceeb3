"""What the tension-only string does to the observed order (part of `python -m benchmark energy`).

With `slack` the elastic potential ½ EA l max(ε, 0)² is only C¹: its second derivative jumps
where an element goes slack or taut, so the smoothness a method's order assumes is lost at those
instants. This measures it: the energy study's scene at N = `ELEMENTS`, with the two-sided
string and with `slack`, over `T_END` s (elements go slack in it), each method of `METHODS` at the
steps `DTS`; the error is the largest body-position difference over the saved times against
`REFERENCE_SETTINGS` (DOP853, far more accurate than the finest step), with the largest energy
error beside it, and the observed order is that of each halving (`benchmark.core.order`). Table:
energy_slack_orders.csv, read by `benchmark.studies.properties` for the energy section.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from reelbench.benchmark.core.order import successive_orders

ELEMENTS = 10
T_END = 10.0
SAVE_EVERY = 0.1
DTS = (0.01, 0.005, 0.0025, 0.00125)
#: the second-order LGVI, its fourth-order composition (Suzuki: stable at every step of `DTS`) and RATTLE
METHODS = ("lgvi", "lgvi_suzuki4", "rattle")
REFERENCE = "dop853"
REFERENCE_SETTINGS = {"rtol": 1e-12, "atol": 1e-14}
TABLE = "energy_slack_orders.csv"


def _scene(variant: str, scene: str, elements: int):
    from reelbench.benchmark.studies.horizon import variant_overrides
    from reelbench.models import load_scene

    base = load_scene(scene, elements=elements)
    return load_scene(scene, elements=elements, **dict(variant_overrides(base, variant)))


def study(out: Path, scene: str = "fixed_length", log: Callable[[str], None] = print,
          elements: int = ELEMENTS) -> Path:
    """Run the measurement and write ``out``/`TABLE` (one row per variant, method and step; the
    position error and energy error are NaN for a run that did not finish)."""
    from reelbench.benchmark.runs.metrics import body_positions, energy_history
    from reelbench.integrators import get_integrator
    from reelbench.models import build_model
    from reelbench.models.diagnostics import evaluate

    rows = []
    for variant in ("", "slack"):
        sc = _scene(variant, scene, elements)
        model = build_model(sc)
        ref = get_integrator(REFERENCE).solve(sc, t_end=T_END, save_every=SAVE_EVERY, **REFERENCE_SETTINGS)
        ref_pos = body_positions(model, ref)
        slack_share = float(np.mean(evaluate(sc, ref)["tension_min"].to_numpy() <= 0.0))
        for name in METHODS:
            for dt in DTS:
                tr = get_integrator(name).solve(sc, t_end=T_END, save_every=SAVE_EVERY, dt=dt)
                err, en = np.nan, np.nan
                if tr.ok and len(tr.t) == len(ref.t):
                    err = float(np.linalg.norm(body_positions(model, tr) - ref_pos, axis=1).max())
                    en = float(energy_history(sc, tr)["energy_error"].max())
                rows.append({"scene": sc.name + (f"_{variant}" if variant else ""), "elements": elements,
                             "integrator": name, "dt": dt,
                             "status": tr.status, "position_error": err,
                             "energy_error": en,
                             "reference_slack_share": slack_share})
            log(f"slack orders: {name} on {rows[-1]['scene']} done")
    table = pd.DataFrame(rows).assign(code=code_key())
    path = Path(out) / TABLE
    table.to_csv(path, index=False)
    return path


def code_key() -> str:
    """The code the table depends on: the models, integrators and this module."""
    from reelbench.benchmark.core import store

    return store.key_of(store.code_version(), store.source_hash((), ("benchmark/studies/slack_orders.py",)))


def fresh(out: Path) -> bool:
    """Whether ``out``/`TABLE` was made by this code (then `study` need not run again)."""
    try:
        return set(pd.read_csv(Path(out) / TABLE)["code"].astype(str)) == {code_key()}
    except Exception:  # noqa: BLE001 - missing or unreadable: not fresh
        return False


def orders(table: pd.DataFrame) -> pd.DataFrame:
    """Observed orders of ``table`` (`study`): per scene and method, the order between each pair
    of halved steps (`benchmark.core.order.successive_orders`), in position and in energy."""
    out = []
    for (scene, name), g in table.groupby(["scene", "integrator"], sort=False):
        g = g.sort_values("dt", ascending=False)
        dt, pos, en = g["dt"].to_numpy(float), g["position_error"].to_numpy(float), g["energy_error"].to_numpy(float)
        out.append({"scene": scene, "integrator": name,
                    "position_orders": successive_orders(dt, pos), "energy_orders": successive_orders(dt, en),
                    "slack_share": float(g["reference_slack_share"].iloc[0])})
    return pd.DataFrame(out)

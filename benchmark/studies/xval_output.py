"""What the cross-validation (`benchmark.studies.xval`) keeps in its output directory beside its
table ``cost.csv``, and how it reads an earlier study there (`Output`).

- ``tips.npz``: every run's tip trajectory, which a CSV cannot hold. It is written before each
  save of the table (`Output.save_tips`, the runner's `Study.beside`), so every saved row has its tips.
- An earlier study: its rows get their tips back from tips.npz (`Output.read_earlier`). A run of
  another (case, N), which this run does not recompute, is kept as it was when it can join this
  study: the same scene and horizon, tips at the same times, and the same scene values (the physics
  hash of each run in ``settings.json``). Otherwise the study is refused before any work, since
  writing would drop it. A run of this study's own (case, N) without its tips is recomputed.
- The report: the other tables, plots, inputs, settings.json and README, from the whole table
  (`benchmark.studies.xval_report.write_report`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from reelbench.benchmark.core.report import Provenance
from reelbench.benchmark.core.store import UnreadableFile, read_npz, write_npz
from reelbench.benchmark.studies.xval import case_scene, output_times, runs_of
from reelbench.models.scene import Scene

TIPS = "tips.npz"
SETTINGS = "settings.json"


def tip_name(case: str, N: int, code: str) -> str:
    """The name of a run's tips in tips.npz."""
    return f"{case}_N{int(N)}_{code}"


class Output:
    """The output directory ``out`` of one xval study: ``scene`` to ``t_end``, its (case, N) jobs
    ``this_run``. ``kept``: the settings entries of the earlier runs it keeps as they were."""

    def __init__(self, out: Path, scene: Scene, t_end: float, this_run: set, log: Callable[[str], None]):
        self.out, self.scene, self.t_end, self.this_run, self.log = Path(out), scene, t_end, set(this_run), log
        self.times = output_times(t_end)
        self.kept: dict = {}

    def save_tips(self, out: Path, rows: list[dict]) -> None:
        """tips.npz of the table rows ``rows`` (each with its ``tip``), atomically."""
        write_npz(Path(out) / TIPS, {"times": self.times, **{tip_name(r["case"], r["N"], r["code"]): r["tip"]
                                                             for r in rows}}, compressed=True)

    def report(self, out: Path, rows: list[dict], provenance: Provenance) -> str:
        """The study's other files from the whole table (`Study.report`)."""
        from reelbench.benchmark.studies import xval_report

        readme = xval_report.write_report(runs_of(rows, self.t_end), self.scene, Path(out), provenance, kept=self.kept)
        return f"wrote {readme}"

    def read_earlier(self, df):
        """The earlier table ``df`` (`Study.read_earlier`) with each row's ``tip``; the rows of this
        run's jobs that lack their tips left out (recomputed); ValueError when it holds runs of
        other (case, N) that cannot be kept (see the module's docstring)."""
        import pandas as pd

        if df.empty:
            return df
        jobs = [(str(c), int(n)) for c, n in zip(df["case"], df["N"])]
        outside = sorted(set(jobs) - self.this_run)
        tips = self._tips()
        if outside:
            self._check(outside, tips)
        elif tips is None or not self._same_times(tips):
            tips = {}  # this run recomputes every job
        tip = [tips.get(tip_name(c, n, code)) for (c, n), code in zip(jobs, df["code"].astype(str))]
        lacking = {job for job, t in zip(jobs, tip) if t is None}
        lost = [f"{code} for {c} N={n}" for (c, n), code, t in zip(jobs, df["code"], tip) if t is None and (c, n) in outside]
        if lost:
            raise self._refuse(f"no tips of {lost[0]} in {TIPS}")
        if outside:
            self.log(f"xval: kept {len(outside)} earlier (case, N) run(s) of {self.out}/ as they were: "
                     + ", ".join(f"{c} N={n}" for c, n in outside))
        df = df.assign(tip=pd.Series(tip, index=df.index, dtype=object))
        return df[pd.Series([job not in lacking for job in jobs], index=df.index, dtype=bool)]

    def _tips(self) -> dict | None:
        """The tips of the earlier study (None when there are none or they cannot be read)."""
        path = self.out / TIPS
        if not path.exists():
            return None
        try:
            return read_npz(path)
        except (OSError, ValueError, UnreadableFile):
            return None

    def _same_times(self, tips: dict) -> bool:
        t = tips.get("times")
        return t is not None and np.shape(t) == self.times.shape and bool(np.allclose(t, self.times))

    def _refuse(self, why: str) -> ValueError:
        return ValueError(f"{self.out} holds an earlier cross-validation that this run cannot merge with and would "
                          f"overwrite ({why}): give --elements (and --scenes, --t-end) covering it, another --out, "
                          "or move it away")

    def _check(self, outside: list[tuple[str, int]], tips: dict | None) -> None:
        """Refuse earlier runs ``outside`` this one that cannot join it; else keep their settings."""
        scene, t_end = self.scene, self.t_end
        try:
            settings = json.loads((self.out / SETTINGS).read_text(encoding="utf-8"))
            earlier = {(str(r["case"]), int(r["N"])): r for r in settings["runs"]}
            if tips is None:
                raise UnreadableFile(f"{TIPS} cannot be read")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise self._refuse(f"its files cannot be read: {type(exc).__name__}") from None
        if settings.get("scene") != scene.name or not np.isclose(float(settings.get("t_end", -1)), t_end):
            raise self._refuse(f"scene {settings.get('scene')!r} to t = {settings.get('t_end')} s, this run's "
                               f"{scene.name!r} to {t_end:g} s")
        if not self._same_times(tips):
            raise self._refuse("its tips are at other times")
        stale = [f"{c} N={n}" for c, n in outside
                 if case_scene(scene, c).with_(elements=n, mass_model="lumped", t_end=t_end).key()
                 != earlier.get((c, n), {}).get("scene_key_lumped")]
        if stale:
            raise self._refuse(f"{', '.join(stale)} computed with other scene values or an older model")
        self.kept = {k: earlier[k] for k in outside}

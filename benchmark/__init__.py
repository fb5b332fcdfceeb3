"""The benchmark: composes scenes, integrators and diagnostics into studies, tables and plots.

    python -m benchmark answer         # the main job: the searched answer and paired timing -> results/
    python -m benchmark run            # the grid sweep of the paper's three scenes -> results/grid/
    python -m benchmark run --quick --out /tmp/quick   # a reduced grid sweep, a few minutes on 2 cores

One subpackage per layer; a package imports only from those listed before it:

- `core`: the job engine (worker processes, this process or Dask; stop signals, progress,
  crash rows), the output store and its lock, what every study does when it writes into a
  directory (`core.study`), JAX-free input checks, the rules stated once (`core.policy`; the
  observed order, `core.order`),
  report provenance, and the one cached reference solution every study compares with;
- `work`: flops, the one work unit, checked against compiled floors (`work.work_rule`);
- `runs`: the runs table: what a sweep runs (`sweep`), one run measured (`runner`, `metrics`),
  what a row may hold and what of an earlier table a run keeps (`table`), and what is read from
  the table (`ranking`, `reproducibility`);
- `figures`: plots and one look per method;
- `answer`: the main job, two studies on `core.study` (`answer`): each method's cheapest
  setting that stands at each target (`search`), the contenders timed in pairs (`paired`), each
  job's run (`jobs`), cheapest.csv (`table`), the answer written (`answer_report`);
- `studies`: the other studies and their writers: the drift check, stability, the energy
  horizon, observed orders, reel reversal, cross-validation against MoorDyn and MuJoCo, speed,
  the grid sweep (`grid`) and its report;
- `contract`: what a plugin integrator or effect must pass (`python -m benchmark verify NAME`);
- `cli`: one module per command (`cli.run`, `cli.check`, ...) parses and checks its input,
  then calls its pipeline in the study's own module (`studies.grid.run_sweep`,
  `studies.check.run_check`, ...); `simulate` and `figures` are the command line's own
  (`cli.simulate`); `cli.main` assembles the commands.

Names from input (scenes, integrators, rows read back) reach a file name only through
`models.io.inside`, which refuses one that leaves its directory (or a link inside it that leads
out).
"""

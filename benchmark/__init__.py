"""The benchmark: composes scenes, integrators and diagnostics into studies, tables and plots.

    python -m benchmark answer         # the main job: the searched answer and paired timing -> results/
    python -m benchmark run            # the grid sweep of the paper's three scenes -> results/grid/
    python -m benchmark run --quick --out /tmp/quick   # a reduced grid sweep, a few minutes on 2 cores

By concern, from the command line down:

- `cli` parses and checks a command's input, then calls its pipeline in `pipelines`;
- the studies, as jobs: `runner` (the runs table), `stability`, `check`, `horizon` (the energy
  study), `orders` (observed orders on a short horizon), `xval`, `lgvi_speed` (speed),
  `reel_reversal`, `answer` (each method's cheapest setting at each target by `search`,
  wall-time verdicts by `paired` timing, racing; N = 10, `--extended` also 40); what a sweep runs: `sweep`; its
  metrics: `metrics`; its work: `flops` (one rule for every method), checked against compiled floors by `work_rule` (results/work_rule.md), whose own arithmetic
  `opcount` counts by running their source on counting scalars;
- their writers: `answer_report`, `runs_report` (the grid sweep's), `horizon_report` (the energy study's figure), `stability_report`,
  `xval_report` (and the baseline in `check`, the speed tables in `lgvi_speed`), on the report
  layer `report` and the plot layer `plots`; what they conclude from: `properties` (energy
  growth classified, orthogonality), `ranking` (what is ranked, work verdicts that call a tie a
  tie, why runs failed), `reproducibility` (two runs tables compared within stated tolerances),
  `styles` (one look per method in every figure);
- the plugin contract: `verify` (`python -m benchmark verify NAME`, and `check_integrator` /
  `check_effect` for a plugin's own tests);
- underneath: `engine` (jobs on worker processes, this process or Dask; stop signals,
  progress with a measured ETA, crash rows), `store` (output lock, resume keys, rows checked
  before they are trusted, a run merged into the table of its --out, atomic tables and .npz files),
  `study_store` (the other studies' rows merged into the tables of their output the same way),
  `reference` (the one cached reference solution every study compares with), `options`
  (JAX-free input checks).

Names from input (scenes, integrators, rows read back) reach a file name only through
`models.io.inside`, which refuses one that leaves its directory (or a link inside it that leads
out); `check` fails (exit 2) on a baseline that would compare nothing or could not fail, and on
one of reelbench's own integrators without baseline rows unless `--allow-new NAME` (a plugin the
baseline does not know is reported, not checked).
"""

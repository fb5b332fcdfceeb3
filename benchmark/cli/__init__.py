"""The command line: one module per command (`run`, `check`, `simulate` with `figures`, `speed`,
`stability`, `answer`, `xval`, `reel_reversal`, `orders`, `energy`, `verify`, `work_rule`,
`listing`), each holding its parser builder (`add_*`) and its function (`cmd_*`: the input
checked, then the pipeline, in the study's own module); `main` assembles them; the options
several commands share are declared once, in `common`."""

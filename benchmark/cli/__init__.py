"""The command line: parsing and checking each command's input (`main`; the options several
commands share are declared once, in `common`), and the one-run commands `simulate` and
`figures` (`simulate`). Every other command calls the pipeline of its study, in
`benchmark.studies` or `benchmark.answer`."""

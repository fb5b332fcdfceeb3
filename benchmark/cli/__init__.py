"""The command line: parsing and checking each command's input (`main`; the options several
commands share are declared once, in `common`), and the pipelines it calls."""

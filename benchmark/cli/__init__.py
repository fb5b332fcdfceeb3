"""The command line: parsing and checking each command's input, and the pipelines it calls."""

"""The runs table: what a sweep runs, how one run is measured, and what is read from the table."""

"""The runs table: what a sweep runs, how one run is measured, what a row may hold and what of an earlier table is kept, and what is read from the table."""

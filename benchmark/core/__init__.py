"""Infrastructure every study stands on: the job engine, the output store and lock, input checks, the rules in one place, report provenance and the shared reference solution."""

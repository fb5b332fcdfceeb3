"""Figures: plots and one look per method."""

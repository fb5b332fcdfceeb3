"""The other studies: the grid sweep, drift check, stability, the energy horizon, observed orders, reel reversal,
cross-validation, speed."""

"""The other studies: drift check, stability, the energy horizon, observed orders, reel reversal, cross-validation, speed."""

"""Simulation: the simulator's and the synthetic anatomy's cost and quality."""

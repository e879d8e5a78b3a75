"""Ablation: what each design choice of the network and the pipeline adds, measured with and without it."""

"""Runnable evaluations of the expert and baselines (reproduce Tables V-VI, Figs. 12-20)."""
